"""The template bank of a recording and its normal equations (:class:`FitProblem`): the
whitened Fourier residual, the noise weights, the linear fit of any set of effects, and
the fit's cache; a set with nonlinear or event effects, or with the nonlinearity acting on
the other effects, goes to :mod:`.backfit` (the likelihood and the methods: :mod:`.`)."""

from __future__ import annotations

import copy
import math

import numpy as np
import scipy.fft
import scipy.optimize

from ..effects import CATALOG, SELECTION_THRESHOLD, Effect
from ..fourier import irfft, rfft
from ..linalg import cross, share_across_detectors, solve_normal
from ..model import Context
from ..noise import NoiseModel, fitted_modes, independent_fraction, periodogram_scale
from . import backfit, frozen
from .results import EffectFit, FitResult

DELTA_BIC_THRESHOLD = SELECTION_THRESHOLD  # effects.base: the effects read it too
GLITCH_THRESHOLD_SIGMA = 5.0
# an offset fitted with the effects when samples are flagged (not reported)
GAP_OFFSET = "gap_offset"


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
        effects = {
            n: e
            for n, e in effects.items()
            if e.min_detectors <= ctx.n_detectors
            and (e.group_by is None or e.group_by in ctx.groups)
        }
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
            residual_f = rfft(residual, axis=-1, workers=workers)
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
        self.bank = np.empty((self.n_det, size, self.freqs.size), dtype=complex)  # every row set
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
                gapped = self.gapped[k]
                for j in range(templates.shape[1]):
                    row = templates[k, j] * self.valid[k] if gapped else templates[k, j]
                    rfft(row, workers=workers, out=self.bank[k, start + j])
            del templates
        self.d_nom_f = rfft(ctx.d_nom, axis=-1, workers=workers)
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
        self._white_variance: dict[int, float] = {}  # white_variance, per detector
        # v_k / S_f: a gapped detector's chi^2 counts its independent modes (module docstring)
        self.w_nom = [
            self.weights(s) * v for s, v in zip(self.s_nom, self.independent, strict=True)
        ]
        size = self.bank.shape[1]
        self.gram_nom, self.rhs_nom, self.yy_nom = [], [], []
        for k in range(self.n_det):
            gram = np.empty((size, size))
            for lo in range(0, size, 8):  # row blocks bound the temporary memory
                # the upper triangle's blocks; the gram is symmetric
                block = cross(self.bank[k][lo : lo + 8], self.bank[k][lo:], self.w_nom[k])
                gram[lo : lo + 8, lo:] = block
                gram[lo:, lo : lo + 8] = block.T
            self.gram_nom.append(gram)
            self.rhs_nom.append(cross(self.bank[k], self.residual_f[k], self.w_nom[k]))
            self.yy_nom.append(
                float(cross(self.residual_f[k][None], self.residual_f[k], self.w_nom[k])[0])
            )
        self._cache: dict[tuple, FitResult] = {}
        self._frozen = None  # the current fit's frozen rows (frozen.FrozenRows), the last asked
        # what an effect derives from the weights once, for every fit (a step search's norms)
        self.derived: dict[tuple, object] = {}

    def with_noise(self, nominal_noise) -> FitProblem:
        """The same problem (template bank, residual) with other noise weights, sharing the bank."""
        other = copy.copy(self)
        other._set_noise(nominal_noise)
        other._cache = {}  # the fits depend on the weights
        other.derived = {}
        return other

    # ------------------------------------------------------------------ helpers
    def masked_rfft(self, tod: np.ndarray) -> np.ndarray:
        """rfft along the last axis of tod (n_det, ..., n) times the valid mask."""
        mask = self.valid.reshape((self.n_det,) + (1,) * (tod.ndim - 2) + (self.n,))
        return rfft(tod * mask, axis=-1, workers=self.workers)

    def white_variance(self, k: int) -> float:
        """Detector k's per-sample noise variance at its nominal PSD's median level over
        the fitted modes, sigma^2 = median(S) f_s / 2 (unscaled), computed once."""
        if k not in self._white_variance:
            median = float(np.median(self.s_nom[k][self.modes]))
            self._white_variance[k] = median / self.scale[k] * self.ctx.sampling_rate_hz / 2
        return self._white_variance[k]

    def valid_mean(self, k: int, spectrum: np.ndarray) -> float:
        """Mean over detector k's valid samples of irfft(spectrum), without the inverse FFT:
        sum_t v_t x_t = (1/n) sum_f c_f Re(X_f V_f*), V = rfft(v), c_f = 2 but at 0 and
        n/2 (Parseval for real sequences)."""
        if not hasattr(self, "_valid_f"):
            self._valid_f = rfft(self.valid.astype(float), axis=-1, workers=self.workers)
            self._parseval_weights = np.full(self._valid_f.shape[-1], 2.0)
            self._parseval_weights[0] = 1.0
            if self.n % 2 == 0:
                self._parseval_weights[-1] = 1.0
        valid_f = self._valid_f[k]
        total = float(
            np.dot(
                self._parseval_weights, spectrum.real * valid_f.real + spectrum.imag * valid_f.imag
            )
        )
        return total / self.n / float(np.count_nonzero(self.valid[k]))

    def _masked_one(self, k: int, spectrum: np.ndarray) -> np.ndarray:
        """rfft(valid_k x irfft(spectrum)): the masked version of an unmasked spectrum."""
        if self.valid[k].all():
            return spectrum
        tod = irfft(spectrum, n=self.n, axis=-1, workers=self.workers)
        return rfft(tod * self.valid[k], axis=-1, workers=self.workers)

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

    def events_of(self, selected) -> list[Effect]:
        """The events effects among ``selected`` (glitches, readout steps), in its order."""
        return [self.effects[n] for n in selected if self.effects[n].kind == "events"]

    def chi2_of(self, k: int, model_f) -> float:
        """Whittle chi^2 of detector k with the problem's noise: sum_f 2 |R_f - M_f|^2 / S_f."""
        diff = self.residual_f[k] - model_f
        return 2 * float((diff.real**2 + diff.imag**2) @ self.w_nom[k])

    def count_parameters(self, selected, event_parameters: dict[str, int]) -> int:
        """The parameters of ``selected``: each effect's per detector or per group, and
        each events effect's ``event_parameters`` (its events' ``n_parameters`` summed)."""
        total = 0
        for name in selected:
            effect = self.effects[name]
            if effect.kind == "events":
                total += event_parameters.get(name, 0)
            elif effect.shared:
                total += len(self.units[name]) * len(effect.shared_groups(self.ctx))
            else:
                total += len(self.units[name]) * self.n_det
        return total

    def prior_penalty(self, selected) -> float:
        return float(sum(self.effects[name].prior_penalty for name in selected))

    def share(self, selected, values, covariances):
        """Impose the shared effects' constraints p_k = s_k r on the per-detector solutions.

        (:func:`.linalg.share_across_detectors`, group by group for an effect shared per
        group; exact for the linear fit.) Returns the new values and covariances and
        {effect: ({group label: (r, sigma_r)}, chi^2 cost)}.
        """
        shared = {}
        if self.n_det < 2:
            return values, covariances, shared
        values, covariances = list(values), list(covariances)
        for name, rows in self._positions(selected).items():
            effect = self.effects[name]
            if not effect.shared:
                continue
            positions = np.arange(rows.start, rows.stop)
            scale = effect.shared_scale(self.ctx)
            scales = np.repeat(scale[:, None], positions.size, axis=1)
            per_group, total_cost = {}, 0.0
            for label, members in effect.shared_groups(self.ctx).items():
                new_values, new_covariances, r, cov_r, cost = share_across_detectors(
                    [values[k] for k in members],
                    [covariances[k] for k in members],
                    positions,
                    scales[members],
                )
                for k, value, covariance in zip(members, new_values, new_covariances, strict=True):
                    values[k], covariances[k] = value, covariance
                per_group[label] = (r, np.sqrt(np.clip(np.diag(cov_r), 0, None)))
                total_cost += cost
            shared[name] = (per_group, total_cost)
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

    def with_shared(self, fits: dict, shared: dict) -> dict:
        """The EffectFits with the shared effects' common values filled in."""
        for name, (per_group, cost) in shared.items():
            effect, fit = self.effects[name], fits[name]
            units = effect.shared_units(self.ctx)

            def named(array, units=units):
                return {p: float(v) for p, v in zip(units, array, strict=True)}

            if effect.group_by is None:
                ((r, sigma),) = per_group.values()
                fit.shared_values, fit.shared_sigmas = named(r), named(sigma)
            else:
                fit.group_values = {label: named(r) for label, (r, _) in per_group.items()}
                fit.group_sigmas = {label: named(s) for label, (_, s) in per_group.items()}
            fit.shared_units = units
            fit.sharing_chi2 = float(cost)
            fit.sharing_dof = len(units) * (self.n_det - len(per_group))
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
            cached = None if keep_model else backfit.nonlinear_screen(self, selected)
            if cached is not None:
                pass
            elif kinds <= {"linear"} and not self.composed(selected):
                cached = self._fit_linear(selected)
            else:
                cached = backfit.fit_composed(self, selected)
            if not keep_model:
                cached.model_f = None
                cached.parts = None
            self._cache[selected] = cached
        return cached

    def response_rows_f(self, k: int, extra: np.ndarray, responses) -> np.ndarray:
        """rfft of valid x the template rows of the response effects ``responses`` (the
        nonlinearity's d^p) for detector k, built on d_nom + ``extra`` (time domain)."""
        signal = self.ctx.d_nom[k] + extra
        templates = np.concatenate([e.response_templates(signal) for e in responses])
        return rfft(templates * self.valid[k], axis=-1, workers=self.workers)

    def trial(self, selected, current: FitResult) -> FitResult:
        """A candidate set: ``current``'s set with one more effect (a forward step) or with
        one in the place of one of its effects (a swap). Its cached fit if there is one;
        else its screen where that shows it cannot pass (:func:`.frozen.frozen_screen`: not
        cached, a later :meth:`fit` fits it in full); else :meth:`fit`."""
        selected = self._ordered(selected)
        if selected not in self._cache:
            screened = frozen.frozen_screen(self, selected, current)
            if screened is not None:
                return screened
        return self.fit(selected)

    def frozen_rows(self, current: FitResult) -> frozen.FrozenRows:
        """The response rows rebuilt on the composed fit ``current`` (the last asked is
        kept: every candidate of a step asks for the same)."""
        if self._frozen is None or self._frozen.composition is not current.composition:
            self._frozen = frozen.FrozenRows(self, current)
        return self._frozen

    def composed(self, selected) -> bool:
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

    def linear_effect_fits(self, selected, values, covariances) -> dict[str, EffectFit]:
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
        values, covariances, shared = self.share(
            selected, [a for a, _ in solved], [cov for _, cov in solved]
        )
        chi2s, models = [], []
        for k in range(self.n_det):
            gram, rhs, a = grams[k], rhss[k], values[k]
            chi2s.append(self.yy_nom[k] - 2 * rhs @ a + a @ gram @ a)
            model = a @ self.bank[k][rows] if rows.size else np.zeros(self.freqs.size, complex)
            models.append(model)
        parts = self.linear_parts(selected, [self.bank[k][rows] for k in range(self.n_det)], values)
        return FitResult(
            selected=selected,
            chi2=float(np.sum(chi2s)),
            chi2_per_detector=np.array(chi2s),
            n_params=self.count_parameters(selected, {}),
            prior_penalty=self.prior_penalty(selected),
            effects=self.with_shared(
                self.linear_effect_fits(selected, values, covariances), shared
            ),
            model_f=models,
            parts=parts,
        )

    def linear_parts(self, selected, banks, values) -> dict:
        """Per-effect Fourier models of the linear effects (rows in ``selected`` order)."""
        return {
            name: [values[k][rows] @ banks[k][rows] for k in range(self.n_det)]
            for name, rows in self._positions(selected).items()
        }

    def residual_after(self, result: FitResult) -> np.ndarray:
        """Time-domain residual after subtracting the fitted model, (n_det, n) (masked)."""
        if result.model_f is None:
            result = self.fit(result.selected, keep_model=True)
        diff = self.residual_f - np.array(result.model_f)
        return irfft(diff, n=self.n, axis=-1, workers=self.workers) * self.valid

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
            out[name] = irfft(diff, n=self.n, axis=-1, workers=self.workers) * self.valid
        return out

    def residual_before(self) -> np.ndarray:
        return irfft(self.residual_f, n=self.n, axis=-1, workers=self.workers)
