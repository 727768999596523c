"""Joint fit of catalog effects to the residual, and forward stepwise selection with the BIC.

Likelihood. Per detector k (detectors' noise independent), with R_f the rfft of the
masked residual r = valid x (recording - d_nom), M_f the rfft of the masked model of the
selected effects and S_f = P(f) n f_s v / 2 the expected periodogram of the noise
(:mod:`.noise`), the Whittle likelihood gives

    chi^2 = sum_k sum_f [ 2 |R_f - M_f|^2 / S_f + 2 ln(S_f / S_f,nom) ],

over the modes f != 0, f_Nyquist (the DC mode is left out: an offset is a nuisance).
With the configured noise (S = S_nom) this is the ordinary chi^2 of the whitened Fourier
coefficients, two real degrees of freedom per mode; ``noise_mismatch`` replaces S_nom by
a fitted S and pays the log-determinant term. N_eff = the number of real Fourier
degrees of freedom used (2 per mode per detector) is the sample size of the

    BIC = chi^2 + k ln N_eff,

k the number of fitted parameters (per detector: each effect's parameters; per glitch:
amplitude, time and tail; per detector for the noise: w, f_knee, alpha).

Fitting a set of effects. Linear effects (templates T_j, :mod:`.effects`): weighted
linear least squares in the whitened Fourier domain, a = G^-1 b with
G_ij = sum_f 2 Re(T_i* T_j) / S_f, b_i = sum_f 2 Re(T_i* R_f) / S_f (columns scaled to
unit diagonal, pseudo-inverse of the normalised G, eigenvalues below 1e-12 dropped);
covariance G^-1. The detector time constant tau: ``scipy.optimize.least_squares`` on the
whitened residual with the linear parameters profiled out (variable projection),
started from the linearised solution (template -d d_nom/dt); covariance of (tau, a) from
the Jacobian, F = J^T J. Glitches: detected in the whitened residual of the other
effects by a robust (MAD) threshold and fitted per event (:func:`.effects.fit_glitch`);
an event is kept if its own Delta chi^2 = (A/sigma_A)^2 exceeds its BIC penalty 3 ln N_eff.
Noise: Whittle maximum likelihood on the residual periodogram (:func:`.noise.whittle_fit`,
line bins excluded from the fit). With nonlinear pieces, the pieces are fitted in turn
(backfitting, three passes).

Selection (:func:`stepwise`). Start from the nominal model (no effect); at each step fit
every remaining effect jointly with the selected ones and compute
Delta BIC = BIC(selected + effect) - BIC(selected); keep the effect with the lowest
Delta BIC (equivalently the largest Delta chi^2 - Delta k ln N_eff) if it is below
``delta_bic_threshold`` (default -10: "very strong" evidence on the Kass & Raftery scale,
a Bayes factor above e^5 ~ 150) and stop otherwise. The lowest Delta BIC is used rather
than the largest Delta chi^2 because an effect with many parameters (hwpss_harmonics: 12
per detector) gains Delta chi^2 from the noise alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.optimize

from .effects import CATALOG, Effect, GlitchEvent, fit_glitch, glitch_tod, single_pole
from .effects import single_pole_derivative
from .model import Context
from .noise import NoiseModel, line_exclusion_mask, periodogram_scale, whittle_fit

DELTA_BIC_THRESHOLD = -10.0
GLITCH_THRESHOLD_SIGMA = 5.0
BACKFIT_PASSES = 3
# Effects on the signal that the detector nonlinearity acts on (applied before it).
COMPOSED_WITH_NONLINEARITY = {
    "detector_time_constant",
    "hwpss_harmonics",
    "hwpss_intensity_coupling",
    "gain_drift",
    "hwp_temperature_drift",
    "crosstalk",
}


def realify(x: np.ndarray) -> np.ndarray:
    """Complex (..., Nf) -> real (..., 2 Nf): [Re, Im]."""
    return np.concatenate([x.real, x.imag], axis=-1)


def solve_normal(gram: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a = G^+ b with unit-diagonal scaling; returns (a, covariance G^+)."""
    k = gram.shape[0]
    a = np.zeros(k)
    cov = np.zeros((k, k))
    if k == 0:
        return a, cov
    diag = np.sqrt(np.clip(np.diag(gram), 0, None))
    good = diag > 0
    cov[~good, ~good] = np.inf
    if not good.any():
        return a, cov
    d = diag[good]
    normalised = gram[np.ix_(good, good)] / np.outer(d, d)
    evals, evecs = np.linalg.eigh(normalised)
    keep = evals > 1e-12 * evals.max()
    inverse = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    a[good] = inverse @ (rhs[good] / d) / d
    cov[np.ix_(good, good)] = inverse / np.outer(d, d)
    return a, cov


@dataclass
class EffectFit:
    """Fitted parameters of one effect: per-detector values and 1-sigma uncertainties."""

    name: str
    values: dict[str, np.ndarray] = field(default_factory=dict)  # parameter -> (n_det,)
    sigmas: dict[str, np.ndarray] = field(default_factory=dict)
    events: list[GlitchEvent] = field(default_factory=list)
    noise: list[NoiseModel] = field(default_factory=list)


@dataclass
class FitResult:
    """The fit of one set of effects."""

    selected: tuple[str, ...]
    chi2: float
    chi2_per_detector: np.ndarray
    n_params: int
    effects: dict[str, EffectFit]
    model_f: list[np.ndarray] = field(repr=False)  # per detector rfft of the masked model
    noise_models: list[NoiseModel] = field(repr=False)
    chi2_off_lines: float = math.nan  # the same chi^2 over the modes away from the lines

    def bic(self, ln_n_eff: float) -> float:
        return self.chi2 + self.n_params * ln_n_eff


class FitProblem:
    """Residual, noise and template bank of a recording; fits any subset of the catalog."""

    def __init__(
        self,
        ctx: Context,
        tod: np.ndarray,
        nominal_noise: list[NoiseModel],
        effects: dict[str, Effect] | None = None,
        glitch_threshold_sigma: float = GLITCH_THRESHOLD_SIGMA,
        workers: int = 1,
    ):
        self.ctx = ctx
        self.workers = workers
        effects = dict(CATALOG if effects is None else effects)
        if ctx.n_detectors < 2:
            effects.pop("crosstalk", None)
        self.effects = effects
        self.glitch_threshold_sigma = glitch_threshold_sigma
        n, fs = ctx.n_samples, ctx.sampling_rate_hz
        self.n = n
        self.freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
        modes = np.ones(self.freqs.size, dtype=bool)
        modes[0] = False
        if n % 2 == 0:
            modes[-1] = False
        self.modes = modes
        self.n_eff = int(2 * modes.sum() * ctx.n_detectors)
        self.ln_n_eff = math.log(self.n_eff)
        resolution = fs / n
        self.line_mask = line_exclusion_mask(
            self.freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * resolution, 2e-4)
        )
        self.valid = np.asarray(ctx.valid, dtype=bool)
        self.all_valid = bool(self.valid.all())
        self.valid_fraction = self.valid.mean(axis=1)
        self.scale = [periodogram_scale(n, fs, v) for v in self.valid_fraction]
        self.nominal_noise = list(nominal_noise)
        self.s_nom = [
            self.scale[k] * nominal_noise[k].psd(self.freqs) for k in range(ctx.n_detectors)
        ]
        residual = np.where(self.valid, tod - ctx.d_nom, 0.0)
        self.residual_f = scipy.fft.rfft(residual, axis=-1, workers=workers)

        # Linear template bank, per detector (rows grouped by effect).
        self.linear_names = [name for name, e in effects.items() if e.kind == "linear"]
        self.slices: dict[str, slice] = {}
        blocks = []
        start = 0
        for name in self.linear_names:
            templates = effects[name].templates(ctx)
            k = templates.shape[1]
            self.slices[name] = slice(start, start + k)
            start += k
            blocks.append(self._masked_rfft(templates))
            del templates
        self.bank = (
            np.concatenate(blocks, axis=1)
            if blocks
            else np.zeros((ctx.n_detectors, 0, self.freqs.size), complex)
        )
        del blocks
        # Time constant: the nominal spectrum (unmasked) and the linearised template.
        self.d_nom_f = scipy.fft.rfft(ctx.d_nom, axis=-1, workers=workers)
        # Nominal-noise Gram matrices of the whole bank: the linear fits are sub-blocks.
        self.gram_nom, self.rhs_nom, self.yy_nom = [], [], []
        for k in range(ctx.n_detectors):
            sw = self.sqrt_weights(self.s_nom[k])
            tw = realify(self.bank[k]) * sw
            yw = realify(self.residual_f[k]) * sw
            self.gram_nom.append(tw @ tw.T)
            self.rhs_nom.append(tw @ yw)
            self.yy_nom.append(float(yw @ yw))
        self._cache: dict[tuple, FitResult] = {}

    # ------------------------------------------------------------------ helpers
    def _masked_rfft(self, tod: np.ndarray) -> np.ndarray:
        """rfft along the last axis of tod (n_det, ..., n) times the valid mask."""
        mask = self.valid.reshape((self.valid.shape[0],) + (1,) * (tod.ndim - 2) + (self.n,))
        return scipy.fft.rfft(tod * mask, axis=-1, workers=self.workers)

    def sqrt_weights(self, s: np.ndarray) -> np.ndarray:
        """sqrt(2 / S_f) on the used modes, 0 elsewhere, realified (2 Nf)."""
        w = np.zeros(self.freqs.size)
        w[self.modes] = np.sqrt(2.0 / s[self.modes])
        return np.concatenate([w, w])

    def rows(self, names) -> np.ndarray:
        idx = [np.arange(self.slices[n].start, self.slices[n].stop) for n in names]
        return np.concatenate(idx) if idx else np.zeros(0, dtype=int)

    def tau_model(self, k: int, tau: float, derivative: bool = False) -> np.ndarray:
        """rfft of valid x IFFT[D (H(tau) - 1)] (or of its tau-derivative)."""
        if derivative:
            spectrum = self.d_nom_f[k] * single_pole_derivative(self.freqs, tau)
        else:
            spectrum = self.d_nom_f[k] * (single_pole(self.freqs, tau) - 1.0)
        if self.all_valid or self.valid[k].all():
            return spectrum
        tod = scipy.fft.irfft(spectrum, n=self.n, workers=self.workers)
        return scipy.fft.rfft(tod * self.valid[k], workers=self.workers)

    def tau_linear_template(self, k: int) -> np.ndarray:
        spectrum = -2j * np.pi * self.freqs * self.d_nom_f[k]
        if self.valid[k].all():
            return spectrum
        tod = scipy.fft.irfft(spectrum, n=self.n, workers=self.workers)
        return scipy.fft.rfft(tod * self.valid[k], workers=self.workers)

    def chi2_of(self, k: int, model_f: np.ndarray, s: np.ndarray, off_lines: bool = False) -> float:
        """Whittle chi^2 of detector k (all used modes, or only those away from the lines)."""
        m = self.modes & ~self.line_mask if off_lines else self.modes
        diff = self.residual_f[k][m] - model_f[m]
        return float(
            np.sum(2 * (diff.real**2 + diff.imag**2) / s[m])
            + np.sum(2 * np.log(s[m] / self.s_nom[k][m]))
        )

    def count_parameters(self, selected, n_events: int) -> int:
        n_det = self.ctx.n_detectors
        total = 0
        for name in selected:
            effect = self.effects[name]
            if effect.kind == "events":
                total += 3 * n_events
            else:
                total += len(effect.parameters) * n_det
        return total

    # ------------------------------------------------------------------ fits
    def fit(self, selected) -> FitResult:
        """Fit the effects ``selected`` jointly (see the module docstring)."""
        order = list(self.effects)
        selected = tuple(sorted(set(selected), key=order.index))
        if selected in self._cache:
            return self._cache[selected]
        kinds = {self.effects[name].kind for name in selected}
        composed = "tes_nonlinearity" in selected and any(
            n in COMPOSED_WITH_NONLINEARITY for n in selected if n != "tes_nonlinearity"
        )
        if kinds <= {"linear"} and not composed:
            result = self._fit_linear(selected)
        else:
            result = self._fit_iterative(selected)
        self._cache[selected] = result
        return result

    def _linear_effect_fits(self, selected, values, covariances) -> dict[str, EffectFit]:
        fits = {}
        n_det = self.ctx.n_detectors
        offset = 0
        for name in selected:
            if name not in self.slices:
                continue
            params = list(self.effects[name].parameters)
            fit = EffectFit(name)
            for j, param in enumerate(params):
                fit.values[param] = np.array([values[k][offset + j] for k in range(n_det)])
                fit.sigmas[param] = np.array(
                    [
                        math.sqrt(max(covariances[k][offset + j, offset + j], 0.0))
                        for k in range(n_det)
                    ]
                )
            offset += len(params)
            fits[name] = fit
        return fits

    def _fit_linear(self, selected) -> FitResult:
        rows = self.rows([n for n in selected if n in self.slices])
        n_det = self.ctx.n_detectors
        values, covariances, chi2s, models = [], [], [], []
        for k in range(n_det):
            gram = self.gram_nom[k][np.ix_(rows, rows)]
            rhs = self.rhs_nom[k][rows]
            a, cov = solve_normal(gram, rhs)
            chi2s.append(self.yy_nom[k] - 2 * rhs @ a + a @ gram @ a)
            values.append(a)
            covariances.append(cov)
            models.append(
                a @ self.bank[k][rows] if rows.size else np.zeros(self.freqs.size, complex)
            )
        return FitResult(
            selected=selected,
            chi2=float(np.sum(chi2s)),
            chi2_per_detector=np.array(chi2s),
            n_params=self.count_parameters(selected, 0),
            effects=self._linear_effect_fits(selected, values, covariances),
            model_f=models,
            noise_models=list(self.nominal_noise),
            chi2_off_lines=sum(
                self.chi2_of(k, models[k], self.s_nom[k], off_lines=True) for k in range(n_det)
            ),
        )

    def _fit_tau(self, k, y_f, tw, sw, start):
        """Variable projection: tau by least_squares, linear parameters profiled out."""
        yw = realify(y_f) * sw
        gram = tw @ tw.T
        if start is None:  # linearised solution: template -d d_nom/dt with the others
            lin = realify(self.tau_linear_template(k)) * sw
            aug = np.vstack([lin[None, :], tw])
            a, _ = solve_normal(aug @ aug.T, aug @ yw)
            start = float(a[0])
        start = float(np.clip(start, 1e-7, 0.5))

        def residual(theta):
            r = yw - realify(self.tau_model(k, theta[0])) * sw
            if tw.shape[0]:
                a, _ = solve_normal(gram, tw @ r)
                r = r - a @ tw
            return r

        solution = scipy.optimize.least_squares(
            residual, [start], bounds=([0.0], [1.0]), x_scale=[max(start, 1e-4)], method="trf"
        )
        tau = float(solution.x[0])
        r = yw - realify(self.tau_model(k, tau)) * sw
        a, _ = solve_normal(gram, tw @ r) if tw.shape[0] else (np.zeros(0), None)
        jac_tau = realify(self.tau_model(k, tau, derivative=True)) * sw
        full = np.vstack([jac_tau[None, :], tw])
        _, cov = solve_normal(full @ full.T, np.zeros(full.shape[0]))
        return tau, math.sqrt(max(cov[0, 0], 0.0)), a, cov[1:, 1:]

    def _detect_glitches(self, k, r_f, s) -> list[GlitchEvent]:
        """Events in the residual r_f (rfft) of detector k: MAD threshold + per-event fit."""
        ctx = self.ctx
        r_time = scipy.fft.irfft(r_f, n=self.n, workers=self.workers) * self.valid[k]
        high = self.freqs > 0.25 * self.freqs[-1]
        s_white = float(np.median(s[high])) if high.any() else float(np.median(s[1:]))
        whitening = np.sqrt(s_white / np.maximum(s, 1e-300))
        whitening[0] = 0.0
        z = scipy.fft.irfft(r_f * whitening, n=self.n, workers=self.workers)
        zv = z[self.valid[k]]
        sigma = 1.4826 * float(np.median(np.abs(zv - np.median(zv))))
        if not sigma > 0:
            return []
        hits = np.flatnonzero((np.abs(z) > self.glitch_threshold_sigma * sigma) & self.valid[k])
        if hits.size == 0:
            return []
        groups = np.split(hits, np.flatnonzero(np.diff(hits) > 10) + 1)
        white_psd = s_white / self.scale[k]
        sigma_sample = math.sqrt(white_psd * ctx.sampling_rate_hz / 2)
        events = []
        penalty = 3 * self.ln_n_eff
        for group in groups[:500]:
            peak = int(group[np.argmax(np.abs(r_time[group]))])
            event = fit_glitch(
                r_time, ctx.times_s, peak, sigma_sample, k, tau_guess_s=1.5 / ctx.sampling_rate_hz
            )
            if event is not None and event.significance**2 > penalty:
                events.append(event)
        return events

    def _nonlinearity_rows(self, selected) -> np.ndarray:
        """Positions of the tes_nonlinearity templates among the selected linear rows."""
        position = 0
        for name in selected:
            if name not in self.slices:
                continue
            size = self.slices[name].stop - self.slices[name].start
            if name == "tes_nonlinearity":
                return np.arange(position, position + size)
            position += size
        return np.zeros(0, dtype=int)

    def _fit_iterative(self, selected) -> FitResult:
        ctx = self.ctx
        n_det = ctx.n_detectors
        linear = [n for n in selected if n in self.slices]
        rows = self.rows(linear)
        has_tau = "detector_time_constant" in selected
        has_glitch = "glitches" in selected
        has_noise = "noise_mismatch" in selected
        # The nonlinearity acts on the total signal: with other signal effects selected, its
        # templates are recomputed on d_nom + (their fitted model) at each pass.
        nl_rows = self._nonlinearity_rows(selected)
        composed = nl_rows.size > 0 and any(
            n in COMPOSED_WITH_NONLINEARITY for n in selected if n != "tes_nonlinearity"
        )
        s = [x.copy() for x in self.s_nom]
        noise_models = list(self.nominal_noise)
        noise_cov = [None] * n_det
        glitch_f = [np.zeros(self.freqs.size, complex) for _ in range(n_det)]
        events: list[GlitchEvent] = []
        tau = [None] * n_det
        tau_sigma = [0.0] * n_det
        values = [np.zeros(rows.size) for _ in range(n_det)]
        covariances = [np.zeros((rows.size, rows.size)) for _ in range(n_det)]
        models = [np.zeros(self.freqs.size, complex) for _ in range(n_det)]
        banks = [self.bank[k][rows] for k in range(n_det)]
        passes = BACKFIT_PASSES if (has_glitch or has_noise or composed) else 1
        for _ in range(passes):
            for k in range(n_det):
                sw = self.sqrt_weights(s[k])
                bank = banks[k]
                tw = realify(bank) * sw if rows.size else np.zeros((0, 2 * self.freqs.size))
                y = self.residual_f[k] - glitch_f[k]
                if has_tau:
                    tau[k], tau_sigma[k], a, cov = self._fit_tau(k, y, tw, sw, tau[k])
                    m_tau = self.tau_model(k, tau[k])
                else:
                    a, cov = solve_normal(tw @ tw.T, tw @ (realify(y) * sw))
                    m_tau = 0.0
                values[k], covariances[k] = a, cov
                linear_model = a @ bank if rows.size else 0.0
                models[k] = linear_model + m_tau + glitch_f[k]
                if composed:
                    others = np.setdiff1d(np.arange(rows.size), nl_rows)
                    signal_f = a[others] @ bank[others] + m_tau
                    signal = ctx.d_nom[k] + scipy.fft.irfft(
                        signal_f, n=self.n, workers=self.workers
                    )
                    banks[k] = bank.copy()
                    banks[k][nl_rows] = scipy.fft.rfft(
                        np.stack([signal**2, signal**3]) * self.valid[k],
                        axis=-1,
                        workers=self.workers,
                    )
            if has_glitch:
                events = []
                for k in range(n_det):
                    events += self._detect_glitches(
                        k, self.residual_f[k] - (models[k] - glitch_f[k]), s[k]
                    )
                glitches = glitch_tod(ctx.times_s, n_det, events)
                for k in range(n_det):
                    new = self._masked_rfft(glitches[k : k + 1])[0]
                    models[k] = models[k] - glitch_f[k] + new
                    glitch_f[k] = new
            if has_noise:
                for k in range(n_det):
                    diff = self.residual_f[k] - models[k]
                    power = diff.real**2 + diff.imag**2
                    fitted = whittle_fit(
                        self.freqs,
                        power,
                        self.modes & ~self.line_mask,
                        self.scale[k],
                        noise_models[k],
                    )
                    noise_models[k] = fitted.model
                    noise_cov[k] = fitted.covariance
                    s[k] = self.scale[k] * fitted.model.psd(self.freqs)
        chi2s = np.array([self.chi2_of(k, models[k], s[k]) for k in range(n_det)])
        fits = self._linear_effect_fits(selected, values, covariances)
        if has_tau:
            fits["detector_time_constant"] = EffectFit(
                "detector_time_constant",
                values={"tau": np.array(tau, dtype=float)},
                sigmas={"tau": np.array(tau_sigma)},
            )
        if has_glitch:
            fits["glitches"] = EffectFit("glitches", events=events)
        if has_noise:
            fit = EffectFit("noise_mismatch", noise=noise_models)
            fit.values = {
                "net": np.array([m.net_k_sqrt_s for m in noise_models]),
                "fknee": np.array([m.fknee_hz for m in noise_models]),
                "alpha": np.array([m.alpha for m in noise_models]),
            }
            sig = [np.sqrt(np.clip(np.diag(c), 0, None)) for c in noise_cov]
            fit.sigmas = {
                "net": fit.values["net"] * np.array([v[0] for v in sig]),
                "fknee": fit.values["fknee"] * np.array([v[1] for v in sig]),
                "alpha": np.array([v[2] for v in sig]),
            }
            fits["noise_mismatch"] = fit
        return FitResult(
            selected=selected,
            chi2=float(chi2s.sum()),
            chi2_per_detector=chi2s,
            n_params=self.count_parameters(selected, len(events)),
            effects=fits,
            model_f=models,
            noise_models=noise_models,
            chi2_off_lines=sum(
                self.chi2_of(k, models[k], s[k], off_lines=True) for k in range(n_det)
            ),
        )

    def residual_after(self, result: FitResult) -> np.ndarray:
        """Time-domain residual after subtracting the fitted model, (n_det, n) (masked)."""
        out = np.empty((self.ctx.n_detectors, self.n))
        for k in range(self.ctx.n_detectors):
            out[k] = scipy.fft.irfft(
                self.residual_f[k] - result.model_f[k], n=self.n, workers=self.workers
            )
        return out * self.valid

    def residual_before(self) -> np.ndarray:
        return scipy.fft.irfft(self.residual_f, n=self.n, axis=-1, workers=self.workers)


@dataclass
class Step:
    """One step of the stepwise selection (an effect added, or the noise model switched)."""

    step: int
    added: str | None
    chi2_before: float
    chi2_after: float
    bic_before: float
    bic_after: float
    n_params_after: int
    candidates: dict[str, dict]  # name -> {"delta_chi2", "delta_bic"}
    note: str = ""

    @property
    def delta_chi2(self) -> float:
        return self.chi2_after - self.chi2_before

    @property
    def delta_bic(self) -> float:
        return self.bic_after - self.bic_before

    def as_dict(self) -> dict:
        return {
            "step": self.step,
            "added": self.added,
            "chi2_before": self.chi2_before,
            "chi2_after": self.chi2_after,
            "delta_chi2": self.delta_chi2,
            "bic_before": self.bic_before,
            "bic_after": self.bic_after,
            "delta_bic": self.delta_bic,
            "n_params_after": self.n_params_after,
            "candidates": self.candidates,
            "note": self.note,
        }


@dataclass
class Selection:
    """Outcome of the stepwise selection."""

    baseline: FitResult
    final: FitResult
    steps: list[Step]
    ln_n_eff: float
    n_eff: int
    threshold: float
    step_delta_chi2: dict[str, float]  # effect -> Delta chi^2 when it was added
    step_delta_bic: dict[str, float]
    drop_one_delta_chi2: dict[str, float]  # chi^2(final without it) - chi^2(final)
    drop_one_delta_bic: dict[str, float]

    @property
    def ranked(self) -> list[str]:
        """Selected effects, most important first (largest drop-one Delta chi^2)."""
        return sorted(self.final.selected, key=lambda n: -self.drop_one_delta_chi2[n])


NOISE = "noise_mismatch"


def noise_delta(problem: FitProblem, templates: tuple, ln_n: float):
    """(fit with nominal noise, fit with fitted noise, Delta chi^2, Delta BIC) off the lines.

    The noise hypothesis is judged on the modes away from the lines (n f_HWP +- m f_spin),
    where only noise should be: a white + 1/f model scaled up would otherwise "explain"
    any large unmodelled line at a fraction of its chi^2.
    """
    nominal = problem.fit(templates)
    fitted = problem.fit(templates + (NOISE,))
    delta_chi2 = fitted.chi2_off_lines - nominal.chi2_off_lines
    delta_k = 3 * problem.ctx.n_detectors
    return nominal, fitted, delta_chi2, delta_chi2 + delta_k * ln_n


def stepwise(
    problem: FitProblem,
    delta_bic_threshold: float = DELTA_BIC_THRESHOLD,
    max_effects: int = 6,
    candidates=None,
) -> Selection:
    """Forward stepwise selection over the catalog with the BIC (module docstring).

    Template effects (all but noise_mismatch) compete by Delta BIC over all modes. The
    noise model is decided before each step, given the effects selected so far: the
    fitted white + 1/f noise replaces the configured one if it lowers the BIC of the
    modes away from the lines by more than the threshold (:func:`noise_delta`); the
    decision is revisited at every step, so a noise model adopted while large effects
    were still unmodelled is dropped once they are.
    """
    ln_n = problem.ln_n_eff
    names = list(problem.effects) if candidates is None else list(candidates)
    names = [n for n in names if n in problem.effects]
    use_noise_candidate = NOISE in names
    template_names = [n for n in names if n != NOISE]
    steps: list[Step] = []
    step_dchi2, step_dbic = {}, {}
    templates: tuple = ()
    baseline = problem.fit(())
    noise_on = False
    noise_dchi2 = noise_dbic = 0.0
    current = baseline
    visited: set = set()
    removed: set = set()
    while True:
        if use_noise_candidate:
            nominal, fitted, noise_dchi2, noise_dbic = noise_delta(problem, templates, ln_n)
            wanted = noise_dbic < delta_bic_threshold
            state = fitted if wanted else nominal
            if wanted != noise_on:
                steps.append(
                    Step(
                        step=len(steps) + 1,
                        added=NOISE if wanted else None,
                        chi2_before=current.chi2,
                        chi2_after=state.chi2,
                        bic_before=current.bic(ln_n),
                        bic_after=state.bic(ln_n),
                        n_params_after=state.n_params,
                        candidates={NOISE: {"delta_chi2": noise_dchi2, "delta_bic": noise_dbic}},
                        note=(
                            "noise model fitted (judged off the lines)"
                            if wanted
                            else "noise model back to the configured one (judged off the lines)"
                        ),
                    )
                )
            noise_on = wanted
            current = state
        if len(templates) >= max_effects:
            break
        remaining = [
            n
            for n in template_names
            if n not in templates and frozenset(templates + (n,)) not in removed
        ]
        if not remaining:
            break
        extra = (NOISE,) if noise_on else ()
        trials = {n: problem.fit(templates + (n,) + extra) for n in remaining}
        table = {
            n: {
                "delta_chi2": t.chi2 - current.chi2,
                "delta_bic": t.bic(ln_n) - current.bic(ln_n),
            }
            for n, t in trials.items()
        }
        best = min(table, key=lambda n: table[n]["delta_bic"])
        accepted = table[best]["delta_bic"] < delta_bic_threshold
        after = trials[best] if accepted else current
        steps.append(
            Step(
                step=len(steps) + 1,
                added=best if accepted else None,
                chi2_before=current.chi2,
                chi2_after=after.chi2,
                bic_before=current.bic(ln_n),
                bic_after=after.bic(ln_n),
                n_params_after=after.n_params,
                candidates=table,
            )
        )
        if not accepted:
            break
        step_dchi2[best] = table[best]["delta_chi2"]
        step_dbic[best] = table[best]["delta_bic"]
        templates = templates + (best,)
        visited.add(frozenset(templates))
        current = after
        # Backward elimination: drop an effect the others have made redundant (its removal
        # costs less than |threshold| in BIC), most redundant first.
        while len(templates) > 1:
            removals = {
                n: problem.fit(tuple(m for m in templates if m != n) + extra) for n in templates
            }
            costs = {n: r.bic(ln_n) - current.bic(ln_n) for n, r in removals.items()}
            weakest = min(costs, key=costs.get)
            reduced = frozenset(m for m in templates if m != weakest)
            if costs[weakest] >= -delta_bic_threshold or reduced in removed:
                break
            removed.add(reduced)
            after = removals[weakest]
            steps.append(
                Step(
                    step=len(steps) + 1,
                    added=None,
                    chi2_before=current.chi2,
                    chi2_after=after.chi2,
                    bic_before=current.bic(ln_n),
                    bic_after=after.bic(ln_n),
                    n_params_after=after.n_params,
                    candidates={
                        weakest: {
                            "delta_chi2": -(current.chi2 - after.chi2),
                            "delta_bic": -costs[weakest],
                        }
                    },
                    note=f"removed {weakest}: made redundant by the effects selected after it",
                )
            )
            templates = tuple(m for m in templates if m != weakest)
            step_dchi2.pop(weakest, None)
            step_dbic.pop(weakest, None)
            current = after
    final = problem.fit(templates + ((NOISE,) if noise_on else ()))
    drop_chi2, drop_bic = {}, {}
    for name in templates:
        without = problem.fit(tuple(n for n in final.selected if n != name))
        drop_chi2[name] = without.chi2 - final.chi2
        drop_bic[name] = without.bic(ln_n) - final.bic(ln_n)
    if noise_on:
        step_dchi2[NOISE] = drop_chi2[NOISE] = -noise_dchi2
        step_dbic[NOISE] = drop_bic[NOISE] = -noise_dbic
        step_dchi2[NOISE] = noise_dchi2
        step_dbic[NOISE] = noise_dbic
    return Selection(
        baseline=baseline,
        final=final,
        steps=steps,
        ln_n_eff=ln_n,
        n_eff=problem.n_eff,
        threshold=delta_bic_threshold,
        step_delta_chi2=step_dchi2,
        step_delta_bic=step_dbic,
        drop_one_delta_chi2=drop_chi2,
        drop_one_delta_bic=drop_bic,
    )
