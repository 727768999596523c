"""Joint fit of catalog effects to the residual, and forward stepwise selection with the BIC.

Likelihood. Per detector k (detectors' noise independent), with R_f the rfft of the
masked residual r = valid x (recording - d_nom), M_f the rfft of the masked model of the
selected effects and S_f = P(f) n f_s v / 2 the expected periodogram of the noise
(:mod:`.noise`), the Whittle likelihood gives

    chi^2 = sum_k v_k sum_f 2 |R_f - M_f|^2 / S_f,

over the modes f != 0, f_Nyquist (the DC mode is left out: an offset is a nuisance),
v_k the detector's fraction of valid samples: a gap correlates the modes, n of them hold
n v independent ones (:func:`.noise.independent_fraction`), and for white noise this
chi^2 is the time-domain one over the valid samples.
With the noise weights S the ordinary chi^2 of the whitened Fourier coefficients, two real
degrees of freedom per mode (the noise is a nominal adjustment, fitted before the effects
and refitted on the residual of the best fit by :mod:`.pipeline`; the fit takes it as
given: ``with_noise``). N_eff = the number of real Fourier
degrees of freedom used (2 v_k per mode per detector) is the sample size of the

    BIC = chi^2 + k ln N_eff,

k the number of fitted parameters (per detector: each effect's parameters; per glitch:
amplitude, time and tail).

Fitting a set of effects. Each effect says how it is fitted by its ``kind``: "linear"
(templates), "nonlinear" (one parameter with a model of its own: the time constant),
"events" (a detector and a per-event fit: glitches); the fit names no effect.
Linear effects (templates T_j, :mod:`.effects`): weighted
linear least squares in the whitened Fourier domain, a = G^-1 b with
G_ij = sum_f 2 Re(T_i* T_j) / S_f, b_i = sum_f 2 Re(T_i* R_f) / S_f (columns scaled to
unit diagonal, pseudo-inverse of the normalised G, eigenvalues below 1e-12 dropped);
covariance G^-1. A nonlinear effect (the detector time constant tau):
``scipy.optimize.least_squares`` on the whitened residual with the linear parameters
profiled out (variable projection), started from the linearised solution (its
``linearised_f``: for tau the template -d d_nom/dt); covariance of (tau, a) from the
Jacobian, F = J^T J. Events (glitches): detected in the whitened residual of the other
effects by a robust (MAD) threshold and fitted per event (:mod:`.effects.glitches`);
an event is kept if its own Delta chi^2 = (A/sigma_A)^2 exceeds its BIC penalty 3 ln N_eff.
The nonlinearity acts on the total signal: its templates (d^2, and d^3 for the cubic
term) are recomputed on d = d_nom + (the fitted model of the other signal effects and of
the nominal adjustments refitted beside it) (the full forward model to second order, e.g.
a gain drift modulating the 4f line; and the pre-nonlinearity model: d_nom was adjusted
to a recording that holds the nonlinearity's own DC and 2f terms, which the refitted
adjustments take out), unless that cross term is below Delta chi^2 = 0.01; in
later passes they are rebuilt only when the fitted model moved enough since the last
build for the same term, 2 g1 d_nom (change of the model), to reach Delta chi^2 = 0.01
(a one-day pair: 125 -> 99 s, the same selection and chi^2). With nonlinear pieces, the
pieces are fitted in turn (backfitting, up to four passes, until chi^2 changes by less
than 0.05). Speed-up: the nonlinear fit is skipped when even
its linearised template, fitted beside the linear effects, gains less than half of its
BIC penalty plus |threshold| (a large tau, where the linearisation fails, gains a lot).

Selection (:func:`stepwise`). Start from the nominal model (no effect); at each step fit
every remaining effect jointly with the selected ones and compute
Delta BIC = BIC(selected + effect) - BIC(selected); keep the effect with the lowest
Delta BIC (equivalently the largest Delta chi^2 - Delta k ln N_eff) if it is below
``delta_bic_threshold`` (default -10: "very strong" evidence on the Kass & Raftery scale,
a Bayes factor above e^5 ~ 150) and stop otherwise. The lowest Delta BIC is used rather
than the largest Delta chi^2 because an effect with many parameters (hwpss_slow_modulation:
up to 24 per detector) gains Delta chi^2 from the noise alone; for the same reason the
HWPSS harmonics are tried line by line (two parameters per detector each, reported
together), and ``max_effects`` counts families, not lines. After each addition, a backward
step removes an effect that the later ones made redundant (its removal raises the BIC by
less than |threshold|); a set once removed is not revisited, so the search ends. Last, a
selected linear signal effect is swapped for an unselected one when that lowers the BIC
(forward selection never revisits its first choice, made with the noise weights of that
moment: an HWP temperature drift taken before the refitted 1/f noise lets a gain drift's
dipole drift show).

Uncertainties: linear parameters from G^-1 (inverse Fisher matrix of the whitened
Fourier fit, which includes the 1/f noise correlations); tau with the linear parameters
from the Jacobian; glitches from the local fit's Jacobian (white noise).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.optimize

from .effects import CATALOG, SELECTION_THRESHOLD, Effect, GlitchEvent
from .linalg import cross, realify, share_across_detectors, solve_normal
from .model import Context
from .noise import NoiseModel, fitted_modes, independent_fraction, periodogram_scale

DELTA_BIC_THRESHOLD = SELECTION_THRESHOLD  # effects.base: the effects read it too
GLITCH_THRESHOLD_SIGMA = 5.0
BACKFIT_PASSES = 4
# with the nonlinearity composed: its templates converge by ~2 g1 A_2 per rebuild
# (g1 A_2 = 0.04: 0.3 % of g1, then 0.02 %, ...) until the cross term is below
# Delta chi^2 = 0.01 (estimated ~6 passes from a cross term of ~1e4; the H3-402 tests at
# g1 A_2 = 0.04 converge within the eight)
COMPOSED_PASSES = 8
# an offset fitted with the effects when samples are flagged (not reported)
GAP_OFFSET = "gap_offset"
CONVERGED_CHI2 = 0.05  # backfitting stops when chi^2 changes by less than this


@dataclass
class EffectFit:
    """Fitted parameters of one effect: per-detector values and 1-sigma uncertainties."""

    name: str
    values: dict[str, np.ndarray] = field(default_factory=dict)  # parameter -> (n_det,)
    sigmas: dict[str, np.ndarray] = field(default_factory=dict)
    events: list[GlitchEvent] = field(default_factory=list)
    # a shared effect (``Effect.shared``): its common parameters, and the chi^2 that sharing
    # them costs against a separate fit per detector, for sharing_dof fewer parameters
    shared_values: dict[str, float] = field(default_factory=dict)
    shared_sigmas: dict[str, float] = field(default_factory=dict)
    shared_units: dict[str, str] = field(default_factory=dict)
    sharing_chi2: float = 0.0
    sharing_dof: int = 0


@dataclass
class FitResult:
    """The fit of one set of effects."""

    selected: tuple[str, ...]
    chi2: float
    chi2_per_detector: np.ndarray
    n_params: int
    effects: dict[str, EffectFit]
    model_f: list[np.ndarray] | None = field(repr=False)  # rfft of the masked model per detector
    parts: dict | None = field(default=None, repr=False)  # effect -> per-detector rfft model

    prior_penalty: float = 0.0  # sum of the selected effects' Effect.prior_penalty

    def bic(self, ln_n_eff: float) -> float:
        return self.chi2 + self.n_params * ln_n_eff + self.prior_penalty


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
        nominal: Effect | None = None,
        residual_f: np.ndarray | None = None,
    ):
        """``residual_f``: the rfft of the residual where(valid, tod - d_nom, 0) if the
        caller has taken it already (computed from ``tod`` otherwise)."""
        self.ctx = ctx
        self.workers = workers
        if effects is None:
            # noise-kind effects are tested on the selection's residual (:mod:`.pipeline`)
            effects = {n: e for n, e in CATALOG.items() if e.selectable and e.kind != "noise"}
        effects = {n: e for n, e in effects.items() if e.min_detectors <= ctx.n_detectors}
        self.effects = effects
        self.nominal = nominal
        self.units = {name: e.param_units(ctx) for name, e in effects.items()}
        self.glitch_threshold_sigma = glitch_threshold_sigma
        n, fs = ctx.n_samples, ctx.sampling_rate_hz
        self.n = n
        self.n_det = ctx.n_detectors
        self.freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
        self.modes = modes = fitted_modes(n)
        self.valid = np.asarray(ctx.valid, dtype=bool)
        # v_k, the fraction of valid samples, plays two parts: each gapped periodogram mode
        # holds v_k independent ones (the likelihood's weight) and v_k scales the
        # periodogram of the zero-filled residual (noise.periodogram_scale)
        self.independent = [independent_fraction(v) for v in self.valid]
        self.n_eff = int(2 * modes.sum() * sum(self.independent))
        self.ln_n_eff = math.log(self.n_eff)
        self.scale = [periodogram_scale(n, fs, v) for v in self.independent]
        if residual_f is None:
            residual = np.where(self.valid, tod - ctx.d_nom, 0.0)
            residual_f = scipy.fft.rfft(residual, axis=-1, workers=workers)
        self.residual_f = residual_f

        # Linear template bank per detector, rows grouped by effect; the nominal
        # adjustments (always fitted, never selected) come first.
        self.linear_names = [name for name, e in effects.items() if e.kind == "linear"]
        self.slices: dict[str, slice] = {}
        size = 0
        # the nominal adjustments' parameters, and an offset when samples are flagged: the
        # offset is fitted before (nominal.fit_nominal) and sits in the DC mode, which the
        # likelihood leaves out; with a gap a constant is no longer a pure DC mode (its
        # masked version leaks to low frequencies), so the constant part of any effect
        # (the nonlinearity's g1 A_2^2 / 2) must be absorbed in the fit itself
        self.gapped = ~self.valid.all(axis=1)
        self.nominal_parameters = [] if nominal is None else list(nominal.parameters)
        if nominal is not None and self.gapped.any():
            self.nominal_parameters.append(GAP_OFFSET)
        self.n_nominal = len(self.nominal_parameters)
        self.nominal_rows = np.arange(self.n_nominal)
        size = self.n_nominal
        for name in self.linear_names:
            k = len(self.units[name])
            self.slices[name] = slice(size, size + k)
            size += k
        self.bank = np.zeros((self.n_det, size, self.freqs.size), dtype=complex)
        sources = [(name, effects[name]) for name in self.linear_names]
        if nominal is not None:
            self.slices[nominal.name] = slice(0, self.n_nominal)
            sources.insert(0, (nominal.name, nominal))
        for name, effect in sources:
            templates = effect.templates(ctx)
            if name == getattr(nominal, "name", None) and GAP_OFFSET in self.nominal_parameters:
                # the offset's row: 1 on a detector with flagged samples, 0 on the others
                # (a parameter without data: solve_normal gives it 0)
                offset_row = np.broadcast_to(self.gapped[:, None, None], (self.n_det, 1, n))
                templates = np.concatenate([templates, offset_row.astype(float)], axis=1)
            start = self.slices[name].start
            for k in range(self.n_det):
                for j in range(templates.shape[1]):
                    self.bank[k, start + j] = scipy.fft.rfft(
                        templates[k, j] * self.valid[k], workers=workers
                    )
            del templates
        self.d_nom_f = scipy.fft.rfft(ctx.d_nom, axis=-1, workers=workers)
        # each nonlinear effect's first-order template per detector (its linearised fit)
        self.linearised_f = {
            name: [
                self._masked_one(k, e.linearised_f(self.freqs, self.d_nom_f[k]))
                for k in range(self.n_det)
            ]
            for name, e in effects.items()
            if e.kind == "nonlinear"
        }
        self._set_noise(nominal_noise)

    def _set_noise(self, nominal_noise) -> None:
        """Noise weights and the normal equations of the whole bank (linear fits take sub-blocks)."""
        self.nominal_noise = list(nominal_noise)
        self.s_nom = [self.scale[k] * nominal_noise[k].psd(self.freqs) for k in range(self.n_det)]
        # v_k / S_f: a gapped detector's chi^2 counts its independent modes (module docstring)
        self.w_nom = [
            self.weights(s) * v for s, v in zip(self.s_nom, self.independent, strict=True)
        ]
        size = self.bank.shape[1]
        self.gram_nom, self.rhs_nom, self.yy_nom = [], [], []
        for k in range(self.n_det):
            gram = np.empty((size, size))
            for lo in range(0, size, 8):  # row blocks bound the temporary memory
                gram[lo : lo + 8] = cross(self.bank[k][lo : lo + 8], self.bank[k], self.w_nom[k])
            self.gram_nom.append(gram)
            self.rhs_nom.append(cross(self.bank[k], self.residual_f[k], self.w_nom[k]))
            self.yy_nom.append(
                float(cross(self.residual_f[k][None], self.residual_f[k], self.w_nom[k])[0])
            )
        self._cache: dict[tuple, FitResult] = {}

    def with_noise(self, nominal_noise) -> FitProblem:
        """The same problem (template bank, residual) with other noise weights, sharing the bank."""
        other = copy.copy(self)
        other._set_noise(nominal_noise)
        other._cache = {}  # the fits depend on the weights
        return other

    # ------------------------------------------------------------------ helpers
    def _masked_rfft(self, tod: np.ndarray) -> np.ndarray:
        """rfft along the last axis of tod (n_det, ..., n) times the valid mask."""
        mask = self.valid.reshape((self.n_det,) + (1,) * (tod.ndim - 2) + (self.n,))
        return scipy.fft.rfft(tod * mask, axis=-1, workers=self.workers)

    def _masked_one(self, k: int, spectrum: np.ndarray) -> np.ndarray:
        """rfft(valid_k x irfft(spectrum)): the masked version of an unmasked spectrum."""
        if self.valid[k].all():
            return spectrum
        tod = scipy.fft.irfft(spectrum, n=self.n, axis=-1, workers=self.workers)
        return scipy.fft.rfft(tod * self.valid[k], axis=-1, workers=self.workers)

    def weights(self, s: np.ndarray) -> np.ndarray:
        """1 / S_f on the used modes, 0 elsewhere."""
        w = np.zeros(self.freqs.size)
        w[self.modes] = 1.0 / s[self.modes]
        return w

    def rows(self, names) -> np.ndarray:
        """Bank rows of the nominal adjustments (always) and of the linear effects ``names``."""
        idx = [self.nominal_rows] + [
            np.arange(self.slices[n].start, self.slices[n].stop) for n in names
        ]
        return np.concatenate(idx).astype(int)

    def nonlinear_model(
        self, effect: Effect, k: int, theta: float, derivative: bool = False
    ) -> np.ndarray:
        """rfft of valid x the change the nonlinear ``effect`` of parameter ``theta`` makes
        to detector k's nominal TOD (or its derivative in theta): ``effect.change_f``."""
        return self._masked_one(k, effect.change_f(self.freqs, self.d_nom_f[k], theta, derivative))

    def nonlinear_of(self, selected) -> Effect | None:
        """The nonlinear effect among ``selected`` (at most one is fitted at a time)."""
        found = [self.effects[n] for n in selected if self.effects[n].kind == "nonlinear"]
        if len(found) > 1:
            raise ValueError(f"{[e.name for e in found]}: one nonlinear effect at a time")
        return found[0] if found else None

    def events_of(self, selected) -> Effect | None:
        """The events effect among ``selected`` (glitches), if any."""
        found = [self.effects[n] for n in selected if self.effects[n].kind == "events"]
        return found[0] if found else None

    def chi2_of(self, k: int, model_f) -> float:
        """Whittle chi^2 of detector k with the problem's noise: sum_f 2 |R_f - M_f|^2 / S_f."""
        diff = self.residual_f[k] - model_f
        return 2 * float((diff.real**2 + diff.imag**2) @ self.w_nom[k])

    def count_parameters(self, selected, n_events: int) -> int:
        total = 0
        for name in selected:
            effect = self.effects[name]
            if effect.kind == "events":
                total += effect.parameters_per_event * n_events
            elif effect.shared:
                total += len(self.units[name])
            else:
                total += len(self.units[name]) * self.n_det
        return total

    def prior_penalty(self, selected) -> float:
        return float(sum(self.effects[name].prior_penalty for name in selected))

    def _share(self, selected, values, covariances):
        """Impose the shared effects' constraints p_k = s_k r on the per-detector solutions.

        (:func:`.linalg.share_across_detectors`; exact for the linear fit.) Returns the new
        values and covariances and {effect: (r, sigma_r, chi^2 cost)}.
        """
        shared = {}
        if self.n_det < 2:
            return values, covariances, shared
        for name, rows in self._positions(selected).items():
            if self.effects[name].shared:
                positions = np.arange(rows.start, rows.stop)
                scale = self.effects[name].shared_scale(self.ctx)
                scales = np.repeat(scale[:, None], positions.size, axis=1)
                values, covariances, r, cov_r, cost = share_across_detectors(
                    values, covariances, positions, scales
                )
                shared[name] = (r, np.sqrt(np.clip(np.diag(cov_r), 0, None)), cost)
        return values, covariances, shared

    def _positions(self, selected) -> dict[str, slice]:
        """Where each linear effect of ``selected`` sits in a fit's parameter vector (the
        bank rows :meth:`rows` takes: the nominal adjustments, then these in order)."""
        positions = {}
        offset = self.n_nominal
        for name in selected:
            if name in self.slices:
                width = self.slices[name].stop - self.slices[name].start
                positions[name] = slice(offset, offset + width)
                offset += width
        return positions

    def _with_shared(self, fits: dict, shared: dict) -> dict:
        """The EffectFits with the shared effects' common values filled in."""
        for name, (r, sigma, cost) in shared.items():
            units = self.effects[name].shared_units(self.ctx)
            fits[name].shared_values = {p: float(v) for p, v in zip(units, r, strict=True)}
            fits[name].shared_sigmas = {p: float(v) for p, v in zip(units, sigma, strict=True)}
            fits[name].shared_units = units
            fits[name].sharing_chi2 = float(cost)
            fits[name].sharing_dof = len(units) * (self.n_det - 1)
        return fits

    def _ordered(self, selected) -> tuple[str, ...]:
        order = list(self.effects)
        return tuple(sorted(set(selected), key=order.index))

    # ------------------------------------------------------------------ fits
    def fit(self, selected, keep_model: bool = False) -> FitResult:
        """Fit the effects ``selected`` jointly (see the module docstring).

        Results are cached; their Fourier model (n_det x N_f complex) is kept only with
        ``keep_model`` (it is refitted when asked for later), to bound the memory.
        """
        selected = self._ordered(selected)
        cached = self._cache.get(selected)
        if cached is None or (keep_model and cached.model_f is None):
            kinds = {self.effects[name].kind for name in selected}
            cached = None if keep_model else self._nonlinear_screen(selected)
            if cached is not None:
                pass
            elif kinds <= {"linear"} and not self._composed(selected):
                cached = self._fit_linear(selected)
            else:
                cached = self._fit_iterative(selected)
            if not keep_model:
                cached.model_f = None
                cached.parts = None
            self._cache[selected] = cached
        return cached

    def _nonlinear_screen(self, selected) -> FitResult | None:
        """Skip the fit of a nonlinear effect when even its linearised template cannot pass.

        With linear effects only besides it, the linearised effect (for tau the template
        -d d_nom/dt, exact to first order) is fitted beside them; if its Delta chi^2 is below
        half its BIC penalty plus |threshold|, it cannot be selected and the fit without it
        is returned (its parameter reported at the linearised value). A large tau, where
        the linearisation is poor, has a huge linearised Delta chi^2 and is fitted.
        """
        effect = self.nonlinear_of(selected)
        if effect is None:
            return None
        name = effect.name
        (parameter,) = effect.parameters
        others = tuple(n for n in selected if n != name)
        if any(self.effects[n].kind != "linear" for n in others) or self._composed(selected):
            return None
        base = self.fit(others)
        rows = self.rows(others)
        delta, taus, sigmas = 0.0, [], []
        for k in range(self.n_det):
            lin = self.linearised_f[name][k][None, :]
            aug = np.vstack([lin, self.bank[k][rows]]) if rows.size else lin
            gram = self.gram_nom[k][np.ix_(rows, rows)] if rows.size else np.zeros((0, 0))
            full = np.zeros((rows.size + 1, rows.size + 1))
            full[1:, 1:] = gram
            full[0] = cross(lin, aug, self.w_nom[k])[0]
            full[:, 0] = full[0]
            rhs = np.concatenate(
                [cross(lin, self.residual_f[k], self.w_nom[k]), self.rhs_nom[k][rows]]
            )
            a, cov = solve_normal(full, rhs)
            chi2 = self.yy_nom[k] - 2 * rhs @ a + a @ full @ a
            delta += base.chi2_per_detector[k] - chi2
            taus.append(a[0])
            sigmas.append(math.sqrt(max(cov[0, 0], 0.0)))
        if delta >= 0.5 * (self.n_det * self.ln_n_eff + abs(DELTA_BIC_THRESHOLD)):
            return None
        effects = dict(base.effects)
        effects[name] = EffectFit(
            name, values={parameter: np.array(taus)}, sigmas={parameter: np.array(sigmas)}
        )
        return FitResult(
            selected=selected,
            chi2=base.chi2,
            chi2_per_detector=base.chi2_per_detector,
            n_params=base.n_params + self.n_det,
            prior_penalty=base.prior_penalty,
            effects=effects,
            model_f=None,
        )

    def _composed(self, selected) -> bool:
        """Does the nonlinearity act on fitted signal? On the other signal effects, and on
        the nominal adjustments refitted beside it: the adjusted model d_nom was fitted to
        the recording WITH the nonlinearity's DC and 2f terms, so d_nom^2 is off by
        ~2 g1 d P(g1 d^2) (P: the adjustments' projection), ~1e-3 of the 4f line at
        g1 A_2 = 0.04; rebuilt on d_nom + the refitted adjustments it converges in one pass
        (a fixed point, rate ~2 g1 A_2)."""
        stages = {self.effects[n].stage for n in selected if n in self.effects}
        if "response" not in stages:
            return False
        return self.n_nominal > 0 or "signal" in stages

    def _linear_effect_fits(self, selected, values, covariances) -> dict[str, EffectFit]:
        """Per-effect values and sigmas; the nominal adjustments under ``self.nominal.name``."""
        fits = {}
        offset = 0
        names = ([self.nominal.name] if self.nominal is not None else []) + list(selected)
        for name in names:
            if name not in self.slices:
                continue
            params = list(
                self.nominal_parameters
                if name == getattr(self.nominal, "name", None)
                else self.units[name]
            )
            fit = EffectFit(name)
            for j, param in enumerate(params):
                i = offset + j
                fit.values[param] = np.array([values[k][i] for k in range(self.n_det)])
                fit.sigmas[param] = np.array(
                    [math.sqrt(max(covariances[k][i, i], 0.0)) for k in range(self.n_det)]
                )
            offset += len(params)
            fits[name] = fit
        return fits

    def _fit_linear(self, selected) -> FitResult:
        rows = self.rows([n for n in selected if n in self.slices])
        grams = [self.gram_nom[k][np.ix_(rows, rows)] for k in range(self.n_det)]
        rhss = [self.rhs_nom[k][rows] for k in range(self.n_det)]
        solved = [solve_normal(gram, rhs) for gram, rhs in zip(grams, rhss, strict=True)]
        values, covariances, shared = self._share(
            selected, [a for a, _ in solved], [cov for _, cov in solved]
        )
        chi2s, models = [], []
        for k in range(self.n_det):
            gram, rhs, a = grams[k], rhss[k], values[k]
            chi2s.append(self.yy_nom[k] - 2 * rhs @ a + a @ gram @ a)
            model = a @ self.bank[k][rows] if rows.size else np.zeros(self.freqs.size, complex)
            models.append(model)
        parts = self._linear_parts(
            selected, [self.bank[k][rows] for k in range(self.n_det)], values
        )
        return FitResult(
            selected=selected,
            chi2=float(np.sum(chi2s)),
            chi2_per_detector=np.array(chi2s),
            n_params=self.count_parameters(selected, 0),
            prior_penalty=self.prior_penalty(selected),
            effects=self._with_shared(
                self._linear_effect_fits(selected, values, covariances), shared
            ),
            model_f=models,
            parts=parts,
        )

    def _linear_parts(self, selected, banks, values) -> dict:
        """Per-effect Fourier models of the linear effects (rows in ``selected`` order)."""
        return {
            name: [values[k][rows] @ banks[k][rows] for k in range(self.n_det)]
            for name, rows in self._positions(selected).items()
        }

    def _fit_nonlinear(self, effect, k, y, bank, gram, w, start):
        """Variable projection: the nonlinear ``effect``'s parameter theta by least_squares
        with the linear parameters profiled out, from its linearised solution.

        Returns (theta, sigma_theta, linear parameters, their covariance).
        """
        sw = np.sqrt(2.0 * w)
        if start is None:
            # the linearised solution: the effect's first-order template beside the others
            lin = self.linearised_f[effect.name][k][None, :]
            aug = np.vstack([lin, bank]) if bank.shape[0] else lin
            a, _ = solve_normal(cross(aug, aug, w), cross(aug, y, w))
            start = float(a[0])
        start = float(np.clip(start, *effect.start_range))

        def residual(theta):
            r = y - self.nonlinear_model(effect, k, theta[0])
            if bank.shape[0]:
                a, _ = solve_normal(gram, cross(bank, r, w))
                r = r - a @ bank
            return realify(r * sw)

        low, high = effect.bounds
        solution = scipy.optimize.least_squares(
            residual, [start], bounds=([low], [high]), x_scale=[max(start, 1e-4)], method="trf"
        )
        theta = float(solution.x[0])
        r = y - self.nonlinear_model(effect, k, theta)
        a = solve_normal(gram, cross(bank, r, w))[0] if bank.shape[0] else np.zeros(0)
        jacobian = self.nonlinear_model(effect, k, theta, derivative=True)[None, :]
        full = np.vstack([jacobian, bank]) if bank.shape[0] else jacobian
        _, cov = solve_normal(cross(full, full, w), np.zeros(full.shape[0]))
        return theta, math.sqrt(max(cov[0, 0], 0.0)), a, cov[1:, 1:]

    def detect_events(self, effect, k: int, r_f: np.ndarray, s: np.ndarray) -> list:
        """The events of ``effect`` (glitches) in the residual r_f (rfft) of detector k, kept
        when their own significance pays their BIC penalty (``parameters_per_event`` ln N_eff)."""
        return effect.detect(
            r_f,
            s,
            self.valid[k],
            self.ctx.times_s,
            self.scale[k],
            k,
            threshold_sigma=self.glitch_threshold_sigma,
            min_significance=math.sqrt(effect.parameters_per_event * self.ln_n_eff),
            workers=self.workers,
        )

    def _fit_iterative(self, selected) -> FitResult:
        """Backfitting of the linear, nonlinear (time constant) and events (glitches) parts
        (module docstring)."""
        ctx = self.ctx
        n_det = self.n_det
        linear = [n for n in selected if n in self.slices]
        rows = self.rows(linear)
        nonlinear = self.nonlinear_of(selected)
        events_effect = self.events_of(selected)
        composed = self._composed(selected)
        nl_rows = np.zeros(0, dtype=int)
        responses = []  # the response effects selected, in bank-row order
        if composed:
            position = self.n_nominal
            for name in linear:
                width = self.slices[name].stop - self.slices[name].start
                if self.effects[name].stage == "response":
                    nl_rows = np.concatenate([nl_rows, np.arange(position, position + width)])
                    responses.append(self.effects[name])
                position += width
        others = np.ones(rows.size)  # 1 on the rows the nonlinearity acts on (not its own)
        others[nl_rows] = 0.0
        events_f = [np.zeros(self.freqs.size, complex) for _ in range(n_det)]
        events: list[GlitchEvent] = []
        theta = [None] * n_det  # the nonlinear effect's parameter per detector
        theta_sigma = [0.0] * n_det
        values = [np.zeros(rows.size) for _ in range(n_det)]
        covariances = [np.zeros((rows.size, rows.size)) for _ in range(n_det)]
        models = [np.zeros(self.freqs.size, complex) for _ in range(n_det)]
        banks = [self.bank[k][rows] for k in range(n_det)]
        recomposed = [False] * n_det  # the nonlinearity rows of banks[k] were recomputed
        built_on = [None] * n_det  # the extra signal they were recomputed with (None: none)
        used_banks = list(banks)
        nonlinear_parts = [0.0] * n_det
        passes = COMPOSED_PASSES if composed else BACKFIT_PASSES if events_effect is not None else 1
        previous_chi2 = math.inf
        for _ in range(passes):
            updated = False  # did the nonlinearity templates change in this pass?
            for k in range(n_det):
                w = self.w_nom[k]
                bank = banks[k]
                gram = self.gram_nom[k][np.ix_(rows, rows)]
                if recomposed[k]:  # else the precomputed block is exact
                    gram[nl_rows] = cross(bank[nl_rows], bank, w)
                    gram[:, nl_rows] = gram[nl_rows].T
                y = self.residual_f[k] - events_f[k]
                if nonlinear is not None:
                    theta[k], theta_sigma[k], a, cov = self._fit_nonlinear(
                        nonlinear, k, y, bank, gram, w, theta[k]
                    )
                    m_nonlinear = self.nonlinear_model(nonlinear, k, theta[k])
                else:
                    a, cov = solve_normal(gram, cross(bank, y, w))
                    m_nonlinear = 0.0
                values[k], covariances[k] = a, cov
                used_banks[k], nonlinear_parts[k] = bank, m_nonlinear
                models[k] = (a @ bank if rows.size else 0.0) + m_nonlinear + events_f[k]
                if composed:  # the nonlinearity acts on d_nom + the other fitted effects
                    signal_f = (a * others) @ bank + m_nonlinear  # no copy of the bank's rows
                    extra = scipy.fft.irfft(signal_f, n=self.n, workers=self.workers)
                    # and the offset before the nonlinearity: the adjusted offset matched the
                    # recorded mean, which holds the model's mean (g1 <d^2> ~ g1 A_2^2 / 2);
                    # left in, it makes 2 g1 O d, which the gain takes and rescales d^2 by
                    # ~4 g1 O (0.3 % of g1 at g1 A_2 = 0.04). The DC mode is not fitted.
                    model = scipy.fft.irfft(a @ bank + m_nonlinear, n=self.n, workers=self.workers)
                    extra -= float(np.mean(model[self.valid[k]]))
                    # chi^2 of the cross term 2 g1 d_nom x (extra - the extra the templates
                    # were last built with): skip the rebuild when negligible
                    change = extra if built_on[k] is None else extra - built_on[k]
                    sigma2 = (
                        float(np.median(self.s_nom[k][self.modes]))
                        / self.scale[k]
                        * ctx.sampling_rate_hz
                        / 2
                    )
                    g1 = a[nl_rows[0]]
                    cross_chi2 = (
                        4
                        * g1**2
                        * float(np.sum((ctx.d_nom[k] * change * self.valid[k]) ** 2))
                        / sigma2
                    )
                    if cross_chi2 < 0.01:
                        continue
                    signal = ctx.d_nom[k] + extra
                    updated = True
                    recomposed[k] = True
                    built_on[k] = extra
                    banks[k] = bank.copy()
                    templates = np.concatenate([e.response_templates(signal) for e in responses])
                    banks[k][nl_rows] = scipy.fft.rfft(
                        templates * self.valid[k],
                        axis=-1,
                        workers=self.workers,
                    )
            values, covariances, shared = self._share(linear, values, covariances)
            if shared:
                for k in range(n_det):
                    models[k] = values[k] @ used_banks[k] + nonlinear_parts[k] + events_f[k]
            if events_effect is not None:
                events = []
                for k in range(n_det):
                    events += self.detect_events(
                        events_effect,
                        k,
                        self.residual_f[k] - models[k] + events_f[k],
                        self.s_nom[k],
                    )
                events = events_effect.detector_events(ctx, events)
                found = self._masked_rfft(events_effect.events_tod(ctx.times_s, n_det, events))
                for k in range(n_det):
                    models[k] = models[k] - events_f[k] + found[k]
                    events_f[k] = found[k]
            if not (updated or events_effect is not None):
                break
            total = sum(self.chi2_of(k, models[k]) for k in range(n_det))
            # while the nonlinearity's templates still move, chi^2 does not tell: it is
            # blind to the scale of d against g1 (g1 (1 + e)^2 d^2 with the gain taking
            # the linear part), which the rebuilds settle at the rate ~2 g1 A_2 per pass
            if abs(previous_chi2 - total) < CONVERGED_CHI2 and not updated:
                break
            previous_chi2 = total
        chi2s = np.array([self.chi2_of(k, models[k]) for k in range(n_det)])
        fits = self._with_shared(self._linear_effect_fits(selected, values, covariances), shared)
        parts = self._linear_parts(selected, used_banks, values)
        if nonlinear is not None:
            (parameter,) = nonlinear.parameters
            fits[nonlinear.name] = EffectFit(
                nonlinear.name,
                values={parameter: np.array(theta, dtype=float)},
                sigmas={parameter: np.array(theta_sigma)},
            )
            parts[nonlinear.name] = nonlinear_parts
        if events_effect is not None:
            fits[events_effect.name] = EffectFit(events_effect.name, events=events)
            parts[events_effect.name] = events_f
        return FitResult(
            selected=selected,
            chi2=float(chi2s.sum()),
            chi2_per_detector=chi2s,
            n_params=self.count_parameters(selected, len(events)),
            prior_penalty=self.prior_penalty(selected),
            effects=fits,
            model_f=models,
            parts=parts,
        )

    def residual_after(self, result: FitResult) -> np.ndarray:
        """Time-domain residual after subtracting the fitted model, (n_det, n) (masked)."""
        if result.model_f is None:
            result = self.fit(result.selected, keep_model=True)
        diff = self.residual_f - np.array(result.model_f)
        return scipy.fft.irfft(diff, n=self.n, axis=-1, workers=self.workers) * self.valid

    def partial_residuals(self, result: FitResult) -> dict[str, np.ndarray]:
        """For each selected effect: the residual minus the OTHER effects' fitted models.

        What the data show of that effect alone, (n_det, n) time domain (masked).
        """
        if result.parts is None:
            result = self.fit(result.selected, keep_model=True)
        total = np.array(result.model_f)
        out = {}
        for name in result.selected:
            own = np.array(result.parts[name]) if name in result.parts else 0.0
            diff = self.residual_f - (total - own)
            out[name] = scipy.fft.irfft(diff, n=self.n, axis=-1, workers=self.workers) * self.valid
        return out

    def residual_before(self) -> np.ndarray:
        return scipy.fft.irfft(self.residual_f, n=self.n, axis=-1, workers=self.workers)


@dataclass
class Step:
    """One step of the selection: an effect added, removed or swapped."""

    step: int
    added: str | None
    removed: str | None
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
            "removed": self.removed,
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
    delta_chi2: dict[str, float]  # effect -> chi^2(final without it) - chi^2(final)
    delta_bic: dict[str, float]  # effect -> BIC(final) - BIC(final without it)  (< 0)

    @property
    def ranked(self) -> list[str]:
        """Selected effects, most important first (largest drop-one Delta chi^2)."""
        return sorted(self.final.selected, key=lambda n: -self.delta_chi2[n])


def _change(current, after, ln_n, **extra) -> dict:
    """A step's candidate entry: Delta chi^2 and Delta BIC from ``current`` to ``after``."""
    return {
        "delta_chi2": after.chi2 - current.chi2,
        "delta_bic": after.bic(ln_n) - current.bic(ln_n),
        **extra,
    }


def _step(steps, current, after, ln_n, candidates, added=None, removed=None, note=""):
    steps.append(
        Step(
            step=len(steps) + 1,
            added=added,
            removed=removed,
            chi2_before=current.chi2,
            chi2_after=after.chi2,
            bic_before=current.bic(ln_n),
            bic_after=after.bic(ln_n),
            n_params_after=after.n_params,
            candidates=candidates,
            note=note,
        )
    )


def _backward(problem, templates, current, threshold, removed_sets, steps, keep=1):
    """Remove the effects that the others made redundant (BIC rises by < |threshold|).

    Stops at ``keep`` effects (1 after a forward step; 0 when checking a start set).
    """
    ln_n = problem.ln_n_eff
    while len(templates) > keep:
        removals = {n: problem.fit(tuple(m for m in templates if m != n)) for n in templates}
        costs = {n: r.bic(ln_n) - current.bic(ln_n) for n, r in removals.items()}
        weakest = min(costs, key=costs.get)
        reduced = frozenset(m for m in templates if m != weakest)
        if costs[weakest] >= -threshold or reduced in removed_sets:
            break
        removed_sets.add(reduced)
        after = removals[weakest]
        _step(
            steps,
            current,
            after,
            ln_n,
            {weakest: {"delta_chi2": after.chi2 - current.chi2, "delta_bic": -costs[weakest]}},
            removed=weakest,
            note=f"{weakest} made redundant by the other effects",
        )
        templates = tuple(m for m in templates if m != weakest)
        current = after
    return templates, current


def select_templates(problem, names, threshold, max_effects, steps: list, initial=()):
    """Forward selection with backward elimination of the template effects ``names``.

    ``initial``: effects to start from (a previous selection, checked first by the
    backward step), instead of the nominal model alone.
    """
    ln_n = problem.ln_n_eff
    templates: tuple = tuple(initial)
    current = problem.fit(templates)
    removed_sets: set = set()
    if templates:
        _step(
            steps,
            problem.fit(()),
            current,
            ln_n,
            {},
            note=f"noise refitted: start again from {list(templates)}",
        )
        templates, current = _backward(
            problem, templates, current, threshold, removed_sets, steps, keep=0
        )
    while len({problem.effects[n].family for n in templates}) < max_effects:
        remaining = [
            n
            for n in names
            if n not in templates and frozenset(templates + (n,)) not in removed_sets
        ]
        if not remaining:
            break
        trials = {n: problem.fit(templates + (n,)) for n in remaining}
        table = {n: _change(current, trial, ln_n) for n, trial in trials.items()}
        for n, trial in trials.items():  # an effect with unphysical parameters is not taken
            why = problem.effects[n].unphysical(trial.effects[n])
            if why is not None:
                table[n]["unphysical"] = why
        allowed = [n for n in table if "unphysical" not in table[n]]
        best = min(allowed, key=lambda n: table[n]["delta_bic"]) if allowed else None
        if best is None or table[best]["delta_bic"] >= threshold:
            _step(steps, current, current, ln_n, table, note="no candidate passes the threshold")
            break
        _step(steps, current, trials[best], ln_n, table, added=best)
        templates += (best,)
        current = trials[best]
        templates, current = _backward(problem, templates, current, threshold, removed_sets, steps)
    templates, current = _swap_look_alikes(problem, names, templates, current, steps)
    templates = _one_family_for_a_line(problem, templates, current, threshold, steps)
    return _without_unphysical(problem, templates, steps)


def _without_unphysical(problem, templates, steps) -> tuple:
    """Remove, one at a time, a selected effect whose parameters the final fit puts outside
    its physical bounds (``Effect.unphysical``): what it absorbed is left to the other
    effects or to ``unexplained``, not reported as its physics."""
    ln_n = problem.ln_n_eff
    current = problem.fit(templates)
    while (out := _first_unphysical(problem, templates, current)) is not None:
        name, why = out
        templates = tuple(t for t in templates if t != name)
        after = problem.fit(templates)
        _step(
            steps,
            current,
            after,
            ln_n,
            {name: _change(current, after, ln_n, unphysical=why)},
            removed=name,
            note=f"{name} removed: its parameters are outside physical bounds ({why})",
        )
        current = after
    return templates


def _first_unphysical(problem, templates, fit) -> tuple[str, str] | None:
    """(name, why) of the first effect of ``templates`` whose parameters in ``fit`` are
    outside its physical bounds, or None."""
    for name in templates:
        if name in fit.effects:
            why = problem.effects[name].unphysical(fit.effects[name])
            if why is not None:
                return name, why
    return None


def _swappable(effect) -> bool:
    return effect.kind == "linear" and effect.stage == "signal"


def _swap_look_alikes(problem, names, templates, current, steps):
    """Replace a selected effect by an unselected one when that lowers the BIC.

    Forward selection never revisits a choice: the effect taken first (with the noise
    weights of that moment) stays even when a look-alike fits better once the noise is
    refitted or the other effects are in, e.g. an HWP temperature drift taken before a
    gain drift whose dipole drift shows only with the refitted 1/f noise. Tried for the
    linear signal effects (cheap fits); each swap is a step naming what it replaced.
    """
    ln_n = problem.ln_n_eff
    seen = {frozenset(templates)}
    while True:
        best = None
        for out in [n for n in templates if _swappable(problem.effects[n])]:
            kept = tuple(t for t in templates if t != out)
            for candidate in names:
                if candidate in templates or not _swappable(problem.effects[candidate]):
                    continue
                if frozenset(kept + (candidate,)) in seen:
                    continue
                trial = problem.fit(kept + (candidate,))
                if problem.effects[candidate].unphysical(trial.effects[candidate]):
                    continue
                gain = trial.bic(ln_n) - current.bic(ln_n)
                if gain < 0 and (best is None or gain < best[3]):
                    best = (out, candidate, trial, gain)
        if best is None:
            return templates, current
        out, candidate, trial, gain = best
        _step(
            steps,
            current,
            trial,
            ln_n,
            {candidate: _change(current, trial, ln_n)},
            added=candidate,
            removed=out,
            note=f"{out} swapped for {candidate}: a lower BIC",
        )
        templates = tuple(t for t in templates if t != out) + (candidate,)
        seen.add(frozenset(templates))
        current = trial


def _one_family_for_a_line(problem, templates, current, threshold, steps):
    """Mechanism parsimony: when a family found line by line (``Effect.reported_as``: the
    HWPSS harmonics) is among the selected effects, an effect whose lines one more member
    of that family fits as well (chi^2 within |threshold|) is replaced by it.

    E.g. lines at f_HWP and at 4 f_HWP, the 4f line in phase with twice the 2f phase and
    no 2 f_HWP +- f_spin sidebands: the nonlinearity fits the 4f line with one parameter
    per detector where the harmonic needs two, but with the harmonics already present
    "two HWPSS lines" is one mechanism where "a line and a nonlinearity" is two. A
    nonlinearity whose sidebands are seen is kept (replacing it raises chi^2 by more).
    """
    ln_n = problem.ln_n_eff
    while True:
        families = {problem.effects[n].reported_as for n in templates} - {None}
        members = [
            m
            for m, e in problem.effects.items()
            if e.reported_as in families and m not in templates
        ]
        others = [n for n in templates if problem.effects[n].reported_as is None]
        best = None
        for name in others:
            kept = tuple(t for t in templates if t != name)
            for member in members:
                trial = problem.fit(kept + (member,))
                if trial.chi2 - current.chi2 < -threshold and (
                    best is None or trial.chi2 < best[2].chi2
                ):
                    best = (name, member, trial)
        if best is None:
            return templates
        name, member, trial = best
        _step(
            steps,
            current,
            trial,
            ln_n,
            {member: _change(current, trial, ln_n)},
            added=member,
            removed=name,
            note=f"{name} replaced by {member}: one family explains the lines as well",
        )
        templates = tuple(t for t in templates if t != name) + (member,)
        current = trial


def stepwise(
    problem: FitProblem,
    delta_bic_threshold: float = DELTA_BIC_THRESHOLD,
    max_effects: int = 6,
    candidates=None,
    initial=(),
) -> Selection:
    """Forward stepwise selection over the catalog with the BIC (module docstring).

    ``initial``: start from these effects (checked by a backward step first).
    """
    ln_n = problem.ln_n_eff
    names = list(problem.effects) if candidates is None else list(candidates)
    names = [n for n in names if n in problem.effects]
    steps: list[Step] = []
    baseline = problem.fit(())
    templates = select_templates(problem, names, delta_bic_threshold, max_effects, steps, initial)
    final = problem.fit(templates)
    delta_chi2, delta_bic = {}, {}
    for name in final.selected:
        without = problem.fit(tuple(n for n in final.selected if n != name))
        delta_chi2[name] = without.chi2 - final.chi2
        delta_bic[name] = final.bic(ln_n) - without.bic(ln_n)
    return Selection(
        baseline=baseline,
        final=final,
        steps=steps,
        ln_n_eff=ln_n,
        n_eff=problem.n_eff,
        threshold=delta_bic_threshold,
        delta_chi2=delta_chi2,
        delta_bic=delta_bic,
    )
