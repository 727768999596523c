"""``diagnose``: nominal model, residual, noise, locate, fit, and the diagnosis report.

    r = recording - d_nom           (d_nom: sky + dipole + A_2 cos 2(chi - theta), :mod:`.model`)
    noise of r                      (robust white + 1/f estimate, :mod:`.noise`)
    where r differs from noise      (lines, HWP-angle harmonics, transients, drifts, sky; :mod:`.locate`)
    which effects explain r         (stepwise selection with the BIC over the catalog; :mod:`.fit`)

Returns the ``diagnosis.json``-shaped dict::

    {"mismatch_found": bool,
     "effects": [{"name", "title", "parameters": {"g1[det]": {"value", "sigma", "unit", ...}},
                  "delta_chi2", "delta_bic", "evidence", ...}, ...],   # ranked
     "chi2_before", "chi2_after", "dof", "n_eff", "delta_bic_threshold",
     "steps": [...], "lines": [...], "noise": {...}, "locate": {...}, "recording": {...}}

"effects" is ranked by the drop-one Delta chi^2 (how much worse the final model gets
without the effect); "delta_bic" is BIC(final) - BIC(final without it) (< 0 for a
selected effect). With ``out_dir``, writes diagnosis.json, diagnosis.md and the figures
(residual spectrum before/after, residual versus HWP angle, residual time series,
residual map).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import scipy.fft

from ..io import atomic_path
from .effects import CATALOG, HWPSS_HARMONICS
from .fit import NOISE, FitProblem, stepwise
from .locate import dc_offset, drifts, hwp_profile, line_at, locate
from .model import build_context, load_sky, nominal_tod, per_detector
from .noise import NoiseModel, estimate_noise, periodogram_scale
from .nominal import (
    NOMINAL,
    SKY_RESIDUAL_NSIDE,
    adjustments_report,
    fit_nominal,
    refit_noise,
)
from .recording import Recording
from .unexplained import find_unexplained

log = logging.getLogger(__name__)
NOISE_REFIT_CHANGE = 0.02  # select again when the noise PSD at the effects moved by > 2 %

__all__ = ["diagnose", "nominal_tod"]


def _nominal_noise_models(recording: Recording, nominal_noise) -> list[NoiseModel]:
    """Noise per detector: from ``nominal_noise`` or the recording's detector metadata.

    ``nominal_noise``: None, (net_ukrts, fknee_mhz, alpha[, fmin_hz]), a dict with those
    keys, a NoiseModel, or a list of one of these per detector.
    """
    n_det = recording.n_detectors
    metadata = recording.nominal_noise()
    if nominal_noise is None:
        items = [None] * n_det
    elif (
        isinstance(nominal_noise, list)
        and len(nominal_noise) == n_det
        and not all(isinstance(x, (int, float)) for x in nominal_noise)
    ):
        items = list(nominal_noise)
    else:
        items = [nominal_noise] * n_det
    models = []
    for k, item in enumerate(items):
        meta = metadata[k]
        if item is None:
            values = meta
        elif isinstance(item, NoiseModel):
            models.append(item)
            continue
        elif isinstance(item, dict):
            values = {**meta, **item}
        else:
            item = tuple(item)
            if len(item) not in (3, 4):
                raise ValueError(
                    f"nominal_noise = {nominal_noise!r}: expected (net_ukrts, fknee_mhz, alpha"
                    "[, fmin_hz])"
                )
            values = dict(meta)
            values.update(zip(("net_ukrts", "fknee_mhz", "alpha", "fmin_hz"), item, strict=False))
        if not (math.isfinite(values["net_ukrts"]) and values["net_ukrts"] > 0):
            # no NET in the file (a lab detector): the noise is a nominal adjustment
            # anyway; it starts from a robust estimate on the residual (see diagnose)
            log.warning(
                "%s: no NET for detector %r in the file: the noise starts from the residual",
                recording.source,
                recording.detector_names[k],
            )
            models.append(None)
            continue
        models.append(NoiseModel.from_detector(values))
    return models


def _fmt(value_k: float) -> str:
    """A temperature in the most readable unit."""
    magnitude = abs(value_k)
    if magnitude >= 1e-1:
        return f"{value_k:.4g} K"
    if magnitude >= 1e-4:
        return f"{value_k * 1e3:.4g} mK"
    return f"{value_k * 1e6:.3g} uK"


class Evidence:
    """Targeted measurements on the residual of one effect, compared with its fitted model.

    ``residual`` is the residual minus the fitted models of the OTHER selected effects
    (what the data show of this effect alone); the harmonics in chi, the DC shift, the
    2f and dipole drifts (:mod:`.locate`) and the lines at 2 f_HWP +- f_spin are measured
    on it, with the noise estimated from the residual.
    """

    def __init__(self, ctx, residual, noise_models, a2, workers=1):
        self.ctx = ctx
        self.residual = residual
        self.noise = noise_models
        self.a2 = a2
        self.workers = workers
        self.f_hwp = ctx.f_hwp_hz
        self.f_spin = ctx.f_spin_hz
        self._harmonics = {}
        self._drifts = {}

    def line(self, k, freq):
        noise = self.noise[k]
        return line_at(
            self.residual[k], self.ctx.times_s, self.ctx.valid[k], freq, float(noise.psd(freq))
        )

    def harmonic(self, k, n):
        if k not in self._harmonics:
            sigma = self.noise[k].net_k_sqrt_s * math.sqrt(self.ctx.sampling_rate_hz)
            self._harmonics[k] = hwp_profile(self.residual[k], self.ctx, k, sigma)[3]
        return self._harmonics[k][n - 1]

    def drift(self, k, quantity):
        if k not in self._drifts:
            ctx = self.ctx
            freqs = scipy.fft.rfftfreq(ctx.n_samples, 1.0 / ctx.sampling_rate_hz)
            scale = periodogram_scale(
                ctx.n_samples, ctx.sampling_rate_hz, float(ctx.valid[k].mean())
            )
            s = scale * self.noise[k].psd(freqs)
            weights = np.zeros(freqs.size)
            weights[1:-1] = 1.0 / s[1:-1]
            residual_f = scipy.fft.rfft(self.residual[k], workers=self.workers)
            self._drifts[k] = {
                d["quantity"]: d for d in drifts(residual_f, ctx, k, weights, self.workers)
            }
        return self._drifts[k][quantity]

    def dipole_amplitude(self, k):
        """Amplitude of the dipole's line at f_spin in the nominal model [K]."""
        return line_at(self.ctx.dipole[k], self.ctx.times_s, self.ctx.valid[k], self.f_spin, 1.0)[0]

    def sidebands(self, k):
        lower = self.line(k, 2 * self.f_hwp - self.f_spin)
        upper = self.line(k, 2 * self.f_hwp + self.f_spin)
        return lower, upper

    def dc(self, k):
        return dc_offset(self.residual[k], self.ctx.valid[k], self.noise[k], self.ctx.duration_s)

    # ---------------------------------------------------------------- per effect
    def tes_nonlinearity(self, fit) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            g1 = fit.values["g1"][k]
            g2 = fit.values["g2"][k]
            a2 = self.a2[k]
            h4 = self.harmonic(k, 4)
            h6 = self.harmonic(k, 6)
            dc, dc_sigma = self.dc(k)
            valid = self.ctx.valid[k]
            d = self.ctx.d_nom[k][valid]
            dc_pred = g1 * float(np.mean(d**2)) + g2 * float(np.mean(d**3))
            (lo, _lo_s, _, lo_sig, *_), (hi, _hi_s, _, hi_sig, *_) = self.sidebands(k)
            side_pred = abs(g1) * a2 * self.dipole_amplitude(k)
            text = (
                f"{name}: 4 f_HWP line {_fmt(h4.amplitude_k)} at {h4.significance_sigma:.1f} sigma "
                f"(predicted g1 A_2^2/2 = {_fmt(abs(g1) * a2**2 / 2)}); DC shift "
                f"{_fmt(dc)} +- {_fmt(dc_sigma)} (predicted {_fmt(dc_pred)}); 2 f_HWP - f_spin and "
                f"2 f_HWP + f_spin lines {_fmt(lo)} and {_fmt(hi)} at {lo_sig:.1f} and "
                f"{hi_sig:.1f} sigma (predicted g1 A_2 D = {_fmt(side_pred)} each)"
            )
            if h6 is not None and abs(fit.sigmas["g2"][k]) > 0:
                text += (
                    f"; 6 f_HWP line {_fmt(h6.amplitude_k)} at {h6.significance_sigma:.1f} sigma "
                    f"(g2 A_2^3/4 = {_fmt(abs(g2) * a2**3 / 4)})"
                )
            parts.append(text)
        return "; ".join(parts)

    def detector_time_constant(self, fit) -> str:
        parts = []
        omega = 2 * np.pi * 2 * self.f_hwp
        for k, name in enumerate(self.ctx.detector_names):
            tau = fit.values["tau"][k]
            static = self.drift(k, "static")
            a2 = self.a2[k]
            c, s = static["hwpss_2f_cos_k"], static["hwpss_2f_sin_k"]
            s_sigma = static["hwpss_2f_sin_sigma_k"]
            lag = math.atan2(s, a2 + c)
            factor = math.hypot(a2 + c, s) / a2 if a2 else math.nan
            lag_pred = math.atan(omega * tau)
            factor_pred = 1 / math.sqrt(1 + (omega * tau) ** 2)
            parts.append(
                f"{name}: the 2 f_HWP HWPSS has a quadrature residual {_fmt(s)} at "
                f"{abs(s) / s_sigma if s_sigma else 0:.0f} sigma, i.e. it lags by "
                f"{lag * 1e3:.3f} mrad with amplitude factor {factor:.6f}; one tau = "
                f"{tau * 1e3:.4g} ms predicts a lag atan(2 pi 2f_HWP tau) = {lag_pred * 1e3:.3f} "
                f"mrad and a factor 1/sqrt(1+(2 pi 2f_HWP tau)^2) = {factor_pred:.6f}"
            )
        return "; ".join(parts)

    def hwpss_harmonics(self, fit) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            found = []
            for n in HWPSS_HARMONICS:
                c, s = fit.values[f"c{n}"][k], fit.values[f"s{n}"][k]
                sigma = max(fit.sigmas[f"c{n}"][k], fit.sigmas[f"s{n}"][k])
                amplitude = math.hypot(c, s)
                if sigma > 0 and amplitude / sigma > 3:
                    found.append(f"{n} f_HWP {_fmt(amplitude)} ({amplitude / sigma:.0f} sigma)")
            dc, dc_sigma = self.dc(k)
            (_lo, _, _, lo_sig, *_), (_hi, _, _, hi_sig, *_) = self.sidebands(k)
            parts.append(
                f"{name}: lines at {', '.join(found) or 'no single harmonic above 3 sigma'}; "
                f"no DC shift ({_fmt(dc)} +- {_fmt(dc_sigma)}) and no 2 f_HWP +- f_spin "
                f"sidebands ({lo_sig:.1f} and {hi_sig:.1f} sigma), unlike a nonlinearity"
            )
        return "; ".join(parts)

    def hwpss_intensity_coupling(self, fit) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            a = math.hypot(fit.values["a2c"][k], fit.values["a2s"][k])
            (lo, _, _, lo_sig, *_), (hi, _, _, hi_sig, *_) = self.sidebands(k)
            h4 = self.harmonic(k, 4)
            a2 = self.a2[k]
            g1_equiv = fit.values["a2c"][k] / (2 * a2) if a2 else math.nan
            parts.append(
                f"{name}: 2 f_HWP - f_spin and 2 f_HWP + f_spin sidebands {_fmt(lo)} and "
                f"{_fmt(hi)} ({lo_sig:.1f} and {hi_sig:.1f} sigma), a = {a:.3g} of I; no 4 f_HWP "
                f"line ({_fmt(h4.amplitude_k)}, {h4.significance_sigma:.1f} sigma) where a "
                f"nonlinearity making the same sidebands (g1 = a/(2 A_2) = {g1_equiv:.3g}/K) "
                f"would give {_fmt(abs(g1_equiv) * a2**2 / 2)}"
            )
        return "; ".join(parts)

    def hwpss_slow_modulation(self, fit) -> str:
        return self.hwp_temperature_drift(fit)

    def gain_drift(self, fit) -> str:
        parts = []
        hours = self.ctx.duration_s / 3600
        for k, name in enumerate(self.ctx.detector_names):
            dipole = self.drift(k, "dipole_gain")
            hwpss = self.drift(k, "hwpss_2f_cos")
            a2 = self.a2[k]
            rel = hwpss["slope_per_hour"] / a2 if a2 else math.nan
            rel_sigma = hwpss["sigma_per_hour"] / a2 if a2 else math.nan
            g1 = fit.values["g1"][k]
            parts.append(
                f"{name}: the dipole amplitude drifts by {dipole['slope_per_hour'] * 100:.3g} +- "
                f"{dipole['sigma_per_hour'] * 100:.2g} %/h ({dipole['significance_sigma']:.1f} "
                f"sigma) together with the 2f HWPSS ({rel * 100:.3g} +- {rel_sigma * 100:.2g} %/h): "
                f"the whole signal scales, as a gain drift g1 P1 (= {2 * g1 / hours * 100:.3g} %/h) "
                "predicts and an HWP temperature drift (2f only) does not"
            )
        return "; ".join(parts)

    def hwp_temperature_drift(self, fit) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            dipole = self.drift(k, "dipole_gain")
            hwpss = self.drift(k, "hwpss_2f_cos")
            parts.append(
                f"{name}: the 2f HWPSS amplitude drifts by {_fmt(hwpss['slope_per_hour'])}/h "
                f"({hwpss['significance_sigma']:.0f} sigma) while the dipole amplitude does not "
                f"({dipole['slope_per_hour'] * 100:.2g} +- {dipole['sigma_per_hour'] * 100:.2g} %/h, "
                f"{dipole['significance_sigma']:.1f} sigma): only the HWP emission changes"
            )
        return "; ".join(parts)

    def glitches(self, fit) -> str:
        events = fit.events
        if not events:
            return "no transient left after the fit"
        strongest = max(events, key=lambda e: e.significance)
        taus = np.array([e.tau_s for e in events])
        names = self.ctx.detector_names
        per_det = {name: sum(e.detector == k for e in events) for k, name in enumerate(names)}
        counts = ", ".join(f"{n} in {name}" for name, n in per_det.items())
        return (
            f"{len(events)} isolated transients ({counts}); the strongest "
            f"{_fmt(strongest.amplitude_k)} at t = {strongest.time_s:.2f} s ({strongest.significance:.0f} "
            f"sigma) in {names[strongest.detector]}; exponential tails tau = "
            f"{np.median(taus) * 1e3:.0f} ms (median); localised in time, not periodic in chi"
        )

    def noise_mismatch(self, fit, nominal: list[NoiseModel], bands) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            m, n = fit.noise[k], nominal[k]
            parts.append(
                f"{name}: NET {m.net_k_sqrt_s * 1e6:.2f} +- {fit.sigmas['net'][k] * 1e6:.2f} uK sqrt(s) "
                f"(configured {n.net_k_sqrt_s * 1e6:.2f}), f_knee {m.fknee_hz * 1e3:.3g} +- "
                f"{fit.sigmas['fknee'][k] * 1e3:.2g} mHz (configured {n.fknee_hz * 1e3:.3g}), alpha "
                f"{m.alpha:.2f} +- {fit.sigmas['alpha'][k]:.2f} (configured {n.alpha:.2f})"
            )
        if bands:
            top = sorted(bands, key=lambda b: -b["significance_sigma"])[:3]
            parts.append(
                "excess broadband power: "
                + ", ".join(
                    f"x{b['power_ratio']:.2f} in {b['f_lo_hz']:.3g}-{b['f_hi_hz']:.3g} Hz "
                    f"({b['significance_sigma']:.0f} sigma, {b['detector']})"
                    for b in top
                )
            )
        parts.append("no template effect needed for it (no lines)")
        return "; ".join(parts)

    def crosstalk(self, fit) -> str:
        parts = []
        for k, name in enumerate(self.ctx.detector_names):
            static = self.drift(k, "static")
            x = fit.values["x"][k]
            a2 = self.a2[k]
            c = static["hwpss_2f_cos_k"]
            g = static["dipole_gain"]
            parts.append(
                f"{name}: the 2f HWPSS changes by {c / a2 if a2 else math.nan:+.3g} of A_2 while "
                f"the dipole changes by {g:+.3g} +- {static['dipole_gain_sigma']:.2g} of itself: "
                f"opposite signs, as the other (orthogonal) detector's signal with x = {x:.4g} "
                "gives (its HWPSS is in antiphase, its dipole in phase)"
            )
        return "; ".join(parts)


def _parameters(name, fit, detector_names, sampling_rate_hz, units) -> dict:
    out = {}
    if name == "glitches":
        for i, e in enumerate(sorted(fit.events, key=lambda e: (e.detector, e.time_s))):
            det = detector_names[e.detector]
            out[f"glitch{i}.amplitude[{det}]"] = {
                "value": e.amplitude_k,
                "sigma": e.sigma_amplitude_k,
                "unit": "K",
                "detector": det,
                "parameter": "amplitude",
            }
            out[f"glitch{i}.time[{det}]"] = {
                "value": e.time_s,
                "sigma": 0.5 / sampling_rate_hz,  # on the sampling grid
                "unit": "s",
                "detector": det,
                "parameter": "time",
            }
            out[f"glitch{i}.tau[{det}]"] = {
                "value": e.tau_s,
                "sigma": e.sigma_tau_s,
                "unit": "s",
                "detector": det,
                "parameter": "tau",
            }
        return out
    for param, unit in units.items():
        for k, det in enumerate(detector_names):
            entry = {
                "value": float(fit.values[param][k]),
                "sigma": float(fit.sigmas[param][k]),
                "unit": unit,
                "detector": det,
                "parameter": param,
            }
            out[f"{param}[{det}]"] = entry
    return out


def _line_table(mismatch, ctx, residual_before, residual_after, noise_models):
    rows = []
    for line in mismatch.lines:
        k = ctx.detector_names.index(line.detector)
        psd = float(noise_models[k].psd(line.freq_hz))
        after = line_at(residual_after[k], ctx.times_s, ctx.valid[k], line.freq_hz, psd)
        rows.append(
            {
                "detector": line.detector,
                "freq_hz": line.freq_hz,
                "identification": line.identification,
                "amplitude_before_k": line.amplitude_k,
                "sigma_k": line.sigma_amplitude_k,
                "significance_before_sigma": line.significance_sigma,
                "global_significance_sigma": line.global_sigma,
                "modulation_before_k": line.modulation_k,
                "modulation_significance_sigma": line.modulation_sigma,
                "amplitude_after_k": after[0],
                "significance_after_sigma": after[3],
            }
        )
    return rows


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def diagnose(
    recording: Recording,
    sky_iqu,
    a2_k,
    nominal_noise=None,
    out_dir=None,
    delta_bic_threshold: float = -10.0,
    max_effects: int = 6,
    workers: int = 1,
    figures: bool = True,
    sky_residual_nside: int | None = SKY_RESIDUAL_NSIDE,
) -> dict:
    """Diagnose ``recording`` against its simulation (module docstring); never told the effect.

    ``sky_iqu``: (3, npix) I, Q, U map [K_CMB, Galactic, RING] or the path of a FITS map;
    ``a2_k``: the nominal HWPSS amplitude A_2 [K] (scalar or one per detector);
    ``nominal_noise``: the configured noise (see :func:`_nominal_noise_models`; default:
    the recording's detector metadata); ``delta_bic_threshold``: an effect is kept if it
    lowers the BIC by more than this (default -10).
    """
    if not isinstance(recording, Recording):
        raise TypeError(f"recording: expected a Recording, got {type(recording).__name__}")
    sky, sky_source = load_sky(sky_iqu)
    a2 = per_detector(a2_k, recording.n_detectors, "a2_k")
    nominal = _nominal_noise_models(recording, nominal_noise)
    base = build_context(recording, sky, a2)
    residual0 = np.where(base.valid, recording.tod - base.d_nom, 0.0)

    estimates = []
    for k in range(base.n_detectors):
        estimates.append(
            estimate_noise(
                residual0[k],
                base.sampling_rate_hz,
                base.valid[k],
                base.f_hwp_hz,
                base.f_spin_hz,
                nominal[k].fmin_hz if nominal[k] is not None else 1e-5,
                start=nominal[k],
            )
        )
    nominal = [m if m is not None else e.model for m, e in zip(nominal, estimates, strict=True)]
    # Nominal adjustments (gain, 2f amplitude and phase, polarisation angle, sky scales,
    # offsets, sky residual, noise): fitted on every recording, never an effect.
    adjusted = fit_nominal(
        base,
        recording.tod,
        nominal,
        sky_residual_nside=sky_residual_nside,
        workers=workers,
    )
    ctx = adjusted.context
    noise_models = adjusted.noise
    residual = np.where(ctx.valid, recording.tod - ctx.d_nom, 0.0)
    mismatch = locate(ctx, residual, noise_models, nominal, workers=workers)

    # The noise was fitted before any effect was removed: a strong effect leaks power
    # beyond the line bins and inflates it. Refit it on the residual of the best fit and,
    # if it moved by more than 2 % where the effects are, select again with the new weights,
    # starting from the effects found (each checked again, then the others tried).
    previous = ()
    history = []
    for attempt in range(2):
        problem = FitProblem(ctx, recording.tod, noise_models, workers=workers, nominal=NOMINAL)
        selection = stepwise(
            problem,
            delta_bic_threshold=delta_bic_threshold,
            max_effects=max_effects,
            initial=previous,
        )
        final = problem.fit(selection.final.selected, keep_model=True)
        history += selection.steps
        if attempt == 1 or not final.selected:
            break
        refit, covariances, change = refit_noise(
            ctx, problem.residual_f - np.array(final.model_f), noise_models
        )
        if change < NOISE_REFIT_CHANGE:
            break
        noise_models = refit
        adjusted.noise, adjusted.noise_covariance = refit, covariances
        previous = final.selected  # checked first with the new weights, then extended
    residual_after = problem.residual_after(final)
    partial = problem.partial_residuals(final)

    effects_out = []
    for name in selection.ranked:
        fit = final.effects[name]
        evidence = Evidence(ctx, partial[name], noise_models, ctx.a2_k, workers)
        if name == NOISE:
            text = evidence.noise_mismatch(fit, nominal, mismatch.excess_bands)
        else:
            text = getattr(evidence, name)(fit)
        effect = CATALOG[name]
        effects_out.append(
            {
                "name": name,
                "title": effect.title,
                "parameters": _parameters(
                    name, fit, ctx.detector_names, ctx.sampling_rate_hz, problem.units[name]
                ),
                "main_parameters": list(effect.main_parameters),
                "delta_chi2": selection.delta_chi2[name],
                "delta_bic": selection.delta_bic[name],
                "evidence": text,
                "signature": effect.signature,
            }
        )
    lines = _line_table(mismatch, ctx, residual, residual_after, noise_models)
    corrections = final.effects[NOMINAL.name]
    adjustments = adjustments_report(
        adjusted, corrections.values, corrections.sigmas, nominal, recording.pol_angles_rad
    )
    n_nuisance = problem.n_nominal * ctx.n_detectors + 3 * ctx.n_detectors + ctx.n_detectors
    n_nuisance += adjusted.sky_residual_pixels
    unexplained = find_unexplained(ctx, residual_after, noise_models, selection, workers)
    result = {
        "mismatch_found": bool(final.selected) or bool(unexplained),
        "effects": effects_out,
        "unexplained": unexplained,
        "nominal_adjustments": adjustments,
        "chi2_before": selection.baseline.chi2,
        "chi2_after": final.chi2,
        "dof": selection.n_eff - final.n_params - n_nuisance,
        "n_nuisance_parameters": n_nuisance,
        "n_eff": selection.n_eff,
        "n_params": final.n_params,
        "bic_before": selection.baseline.bic(selection.ln_n_eff),
        "bic_after": final.bic(selection.ln_n_eff),
        "delta_bic_threshold": delta_bic_threshold,
        "information_criterion": "BIC = chi2 + k ln N_eff (N_eff = real Fourier dof used)",
        "steps": [dict(step.as_dict(), step=i + 1) for i, step in enumerate(history)],
        "lines": lines,
        "noise": {
            "nominal": [
                {
                    "net_k_sqrt_s": m.net_k_sqrt_s,
                    "fknee_hz": m.fknee_hz,
                    "alpha": m.alpha,
                    "fmin_hz": m.fmin_hz,
                }
                for m in nominal
            ],
            "estimated": [e.as_dict() for e in estimates],
            "test_off_lines": selection.noise_test,
        },
        "locate": mismatch.as_dict(),
        "recording": {
            "source": recording.source,
            "channel": recording.channel,
            "detectors": ctx.detector_names,
            "duration_s": recording.duration_s,
            "sampling_rate_hz": recording.sampling_rate_hz,
            "start_time_mjd": float(recording.start_time.mjd),
            "start_time_scale": recording.start_time.scale,
            "flagged_fraction": float(np.mean(recording.flags)),
            "sky": sky_source,
            "a2_k": a2.tolist(),
            "f_hwp_hz": ctx.f_hwp_hz,
        },
    }
    result = _jsonable(result)
    if out_dir is not None:
        write_outputs(
            result,
            out_dir,
            ctx,
            problem,
            residual,
            residual_after,
            mismatch,
            noise_models,
            figures=figures,
        )
    return result


def write_outputs(
    result, out_dir, ctx, problem, residual, residual_after, mismatch, noise_models, figures=True
) -> None:
    """diagnosis.json, diagnosis.md and the PNG figures in ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "diagnosis.json") as temporary:
        temporary.write_text(json.dumps(result, indent=2) + "\n")
    figure_files = {}
    if figures:
        from ..figures import diagnose as fig

        figure_files = fig.diagnosis_figures(
            out_dir, ctx, residual, residual_after, mismatch, noise_models, result
        )
    with atomic_path(out_dir / "diagnosis.md") as temporary:
        temporary.write_text(markdown_report(result, figure_files))


def markdown_report(result: dict, figure_files: dict | None = None) -> str:
    """The human-readable report: what physics was left out, how sure, the evidence."""
    rec = result["recording"]
    out = [
        "# Diagnosis of a recording against its simulation",
        "",
        (
            f"Recording: `{rec['source']}` ({rec['channel']}, detectors {', '.join(rec['detectors'])}, "
            f"{rec['duration_s'] / 3600:.3g} h at {rec['sampling_rate_hz']:g} Hz, "
            f"{100 * rec['flagged_fraction']:.2g} % flagged); A_2 = {rec['a2_k']} K; sky: {rec['sky']}."
        ),
        "",
    ]
    effects = result["effects"]
    unexplained = result.get("unexplained", [])
    if not result["mismatch_found"]:
        out += [
            (
                "**No mismatch found**: once the nominal model's adjustments are fitted (below), "
                "no effect of the catalog lowers the BIC by more than "
                f"{-result['delta_bic_threshold']:g} and no significant structure is left; the "
                f"residual is consistent with the fitted noise (chi2 = {result['chi2_before']:.1f} "
                f"for {result['dof']} degrees of freedom)."
            ),
            "",
        ]
    elif not effects:
        out += [
            (
                "**Mismatch found, but no catalog effect explains it**: see *What the fit "
                "cannot explain* below."
            ),
            "",
        ]
    else:
        out += [
            (
                f"**Mismatch found.** The simulation left out {len(effects)} effect(s); the fit "
                f"lowers chi2 from {result['chi2_before']:.1f} to {result['chi2_after']:.1f} "
                f"(N_eff = {result['n_eff']}, dof = {result['dof']}), BIC from "
                f"{result['bic_before']:.1f} to {result['bic_after']:.1f}."
            ),
            "",
        ]
    for rank, effect in enumerate(effects, 1):
        out += [
            f"## {rank}. {effect['title']} (`{effect['name']}`)",
            "",
            (
                f"*How sure*: removing it from the final model raises chi2 by "
                f"{effect['delta_chi2']:.4g} and the BIC by {-effect['delta_bic']:.4g} "
                f"(threshold {-result['delta_bic_threshold']:g})."
            ),
            "",
            f"*Signature*: {effect['signature']}.",
            "",
            f"*Evidence*: {effect['evidence']}.",
            "",
            "| parameter | value | sigma | unit |",
            "|---|---|---|---|",
        ]
        for pname, p in list(effect["parameters"].items())[:60]:
            out.append(f"| {pname} | {p['value']:.6g} | {p['sigma']:.3g} | {p['unit']} |")
        out.append("")
    out += ["## What the fit cannot explain", ""]
    if unexplained:
        out += [
            (
                "Significant structure left in the residual after the nominal adjustments "
                "and the selected effects; these are NOT forced onto a catalog effect:"
            ),
            "",
        ]
        out += [f"- {entry['text']}." for entry in unexplained]
    else:
        out.append("Nothing: no line, band, time segment or sky region above 5 sigma is left.")
    out += ["", "## Nominal-model adjustments (fitted on every recording, not effects)", ""]
    out += [
        "| detector | quantity | value | sigma | unit | nominal |",
        "|---|---|---|---|---|---|",
    ]
    for det, items in result.get("nominal_adjustments", {}).items():
        for quantity, item in items.items():
            sigma = item["sigma"]
            sigma_text = f"{sigma:.3g}" if sigma is not None else "-"
            out.append(
                f"| {det} | {quantity} | {item['value']:.6g} | {sigma_text} | {item['unit']} | "
                f"{item['nominal']:.6g} |"
            )
    out += [
        "",
        "## Selection steps",
        "",
        "| step | added | removed | chi2 before | chi2 after | BIC before | BIC after | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in result["steps"]:
        out.append(
            f"| {s['step']} | {s['added'] or ''} | {s['removed'] or ''} | {s['chi2_before']:.1f} | "
            f"{s['chi2_after']:.1f} | {s['bic_before']:.1f} | {s['bic_after']:.1f} | {s['note']} |"
        )
    out += [
        "",
        "## Lines in the residual (before and after the fit)",
        "",
        (
            "Amplitudes of the static part of each line; *modulation* is the rms of its slow "
            "amplitude change over the recording (a drifting line)."
        ),
        "",
        (
            "| detector | frequency [Hz] | identification | before | significance | modulation "
            "| after | significance |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for line in result["lines"]:
        out.append(
            f"| {line['detector']} | {line['freq_hz']:.6f} | {line['identification']} | "
            f"{_fmt(line['amplitude_before_k'])} | {line['significance_before_sigma']:.1f} | "
            f"{_fmt(line['modulation_before_k'])} ({line['modulation_significance_sigma']:.1f} "
            f"sigma) | {_fmt(line['amplitude_after_k'])} | {line['significance_after_sigma']:.1f} |"
        )
    out += ["", "## Noise (configured vs estimated from the residual)", ""]
    for nominal, estimated, det in zip(
        result["noise"]["nominal"], result["noise"]["estimated"], rec["detectors"], strict=False
    ):
        out.append(
            f"- {det}: NET {estimated['net_k_sqrt_s'] * 1e6:.2f} uK sqrt(s) (configured "
            f"{nominal['net_k_sqrt_s'] * 1e6:.2f}), f_knee {estimated['fknee_hz'] * 1e3:.3g} mHz "
            f"(configured {nominal['fknee_hz'] * 1e3:.3g}), alpha {estimated['alpha']:.2f} "
            f"(configured {nominal['alpha']:.2f})"
        )
    if figure_files:
        out += ["", "## Figures", ""]
        for title, name in figure_files.items():
            out.append(f"![{title}]({name})")
    return "\n".join(out) + "\n"
