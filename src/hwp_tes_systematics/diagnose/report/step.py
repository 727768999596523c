"""Step 6 of the diagnosis: the :class:`.diagnosis.Diagnosis` of the steps' outputs."""

from __future__ import annotations

import math

import numpy as np

from ..locate import line_at
from ..nominal.adjustments import NOMINAL, adjustments_report
from ..nominal.step import NominalFit
from ..select.step import Selection
from .diagnosis import Diagnosis


def report(
    fit: NominalFit,
    selection: Selection,
    mismatch,
    effects: list[dict],
    unexplained: list[dict],
    requirement_check: dict,
    delta_bic_threshold: float,
) -> Diagnosis:
    """Step 6: the :class:`.report.diagnosis.Diagnosis` (what ``diagnosis.json`` holds; the module
    docstring) of the steps' outputs."""
    recording, ctx, adjusted = fit.recording, fit.context, fit.adjusted
    steps, final, noise_models = selection.steps, selection.final, selection.noise_models
    lines = _line_table(mismatch, ctx, fit.residual, selection.residual_after, noise_models)
    corrections = final.effects[NOMINAL.name]
    adjustments = adjustments_report(
        adjusted, corrections.values, corrections.sigmas, fit.nominal, recording.pol_angles_rad
    )
    n_nuisance = len(NOMINAL.parameters) * ctx.n_detectors + 3 * ctx.n_detectors + ctx.n_detectors
    n_nuisance += adjusted.sky_residual_pixels
    result = {
        "mismatch_found": bool(effects) or bool(unexplained),
        "effects": effects,
        "unexplained": unexplained,
        "nominal_adjustments": adjustments,
        "chi2_before": steps.baseline.chi2,
        "chi2_after": final.chi2,
        "dof": steps.n_eff - final.n_params - n_nuisance,
        "n_nuisance_parameters": n_nuisance,
        "n_eff": steps.n_eff,
        "n_params": final.n_params,
        "bic_before": steps.baseline.bic(steps.ln_n_eff),
        "bic_after": final.bic(steps.ln_n_eff),
        "delta_bic_threshold": delta_bic_threshold,
        "information_criterion": "BIC = chi2 + k ln N_eff (N_eff = real Fourier dof used)",
        "requirement_check": requirement_check,
        "steps": [dict(step.as_dict(), step=i + 1) for i, step in enumerate(selection.history)],
        "swap_margins": {
            "definition": "per selected linear signal effect, BIC with each unselected one in "
            "its place minus the final BIC, under the final fit's noise weights (> 0: the "
            "selected effect is preferred by that much)",
            "effects": selection.swap_margins,
        },
        "lines": lines,
        "noise": {
            "nominal": [
                {
                    "net_k_sqrt_s": m.net_k_sqrt_s,
                    "fknee_hz": m.fknee_hz,
                    "alpha": m.alpha,
                    "fmin_hz": m.fmin_hz,
                }
                for m in fit.nominal
            ],
            "estimated": [e.as_dict() for e in fit.estimates],
            # the noise the final fit weighs with (refitted beside the effects found and a
            # gain fluctuation's sidebands; "estimated" is the recording's before any fit)
            "final": [
                {
                    "net_k_sqrt_s": m.net_k_sqrt_s,
                    "fknee_hz": m.fknee_hz,
                    "alpha": m.alpha,
                    "tau_s": m.tau_s,
                }
                for m in (getattr(m, "base", m) for m in noise_models)
            ],
            "rolloff": selection.rolloff.as_dict(),
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
            "sky": fit.sky_source,
            "a2_k": fit.a2_k.tolist(),
            "f_hwp_hz": ctx.f_hwp_hz,
        },
    }
    return Diagnosis(_jsonable(result))


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
