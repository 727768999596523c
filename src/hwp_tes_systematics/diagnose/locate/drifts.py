"""Where in time: drifts of the offset, the 2f amplitude and the dipole gain, and the DC
offset (:mod:`hwp_tes_systematics.diagnose.locate`, "Time"; transients: :mod:`..effects.glitches`)."""

from __future__ import annotations

import math

import numpy as np

from ..fourier import rfft
from ..linalg import whitened_lstsq
from ..model import Context
from ..noise import (
    NoiseModel,
)


def drifts(
    residual_f: np.ndarray, ctx: Context, k: int, weights: np.ndarray, workers: int = 1
) -> list[dict]:
    """Offset slope, 2f amplitude drift and dipole gain drift of detector k (whitened LS)."""
    p1 = ctx.legendre(1)
    angle = ctx.hwpss_angle[k]  # the (adjusted) 2f carrier phase
    dipole = ctx.dipole[k]
    rows = [
        p1,
        np.cos(angle),
        p1 * np.cos(angle),
        np.sin(angle),
        p1 * np.sin(angle),
        dipole,
        p1 * dipole,
    ]
    templates_f = rfft(np.stack(rows) * ctx.valid[k], axis=-1, workers=workers)
    values, sigmas = whitened_lstsq(residual_f, templates_f, weights)
    hours = ctx.duration_s / 3600.0
    name = ctx.detector_names[k]

    def item(quantity, index, unit, per_hour_factor, description):
        value = float(values[index]) * per_hour_factor
        sigma = float(sigmas[index]) * per_hour_factor
        return {
            "detector": name,
            "quantity": quantity,
            "slope_per_hour": value,
            "sigma_per_hour": sigma,
            "unit": unit,
            "significance_sigma": abs(value) / sigma if sigma > 0 else 0.0,
            "description": description,
        }

    # P1 runs from -1 to +1 over the recording: a slope of 2 c / duration.
    per_hour = 2.0 / hours if hours > 0 else 0.0
    return [
        item("offset", 0, "K/h", per_hour, "residual offset drift"),
        item("hwpss_2f_cos", 2, "K/h", per_hour, "drift of the 2f HWPSS amplitude (in phase)"),
        item("hwpss_2f_sin", 4, "K/h", per_hour, "drift of the 2f HWPSS (quadrature)"),
        item("dipole_gain", 6, "1/h", per_hour, "drift of the dipole amplitude (relative)"),
        {
            "detector": name,
            "quantity": "static",
            "hwpss_2f_cos_k": float(values[1]),
            "hwpss_2f_cos_sigma_k": float(sigmas[1]),
            "hwpss_2f_sin_k": float(values[3]),
            "hwpss_2f_sin_sigma_k": float(sigmas[3]),
            "dipole_gain": float(values[5]),
            "dipole_gain_sigma": float(sigmas[5]),
        },
    ]


def dc_offset(residual: np.ndarray, valid: np.ndarray, noise: NoiseModel, duration_s: float):
    """Mean of the residual and its uncertainty sqrt(P(1/T) / T) (1/f noise at the longest scale)."""
    mean = float(residual[valid].mean())
    sigma = math.sqrt(float(noise.psd(1.0 / duration_s)) / duration_s)
    return mean, sigma
