"""Where in HWP angle: the residual binned in chi and its harmonics
(:mod:`hwp_tes_systematics.diagnose.locate`, "HWP angle")."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..model import Context
from .frequency import MAX_HARMONIC

HWP_BINS = 64


@dataclass
class Harmonic:
    detector: str
    n: int
    amplitude_k: float
    sigma_k: float
    phase_rad: float
    significance_sigma: float

    def as_dict(self) -> dict:
        return asdict(self)


def hwp_profile(residual: np.ndarray, ctx: Context, k: int, sigma_sample: float):
    """(bin centres, mean residual per chi bin, its sigma, harmonics n = 1..8)."""
    valid = ctx.valid[k]
    chi = np.mod(ctx.hwp_angle_rad[valid], 2 * np.pi)
    r = residual[valid]
    edges = np.linspace(0, 2 * np.pi, HWP_BINS + 1)
    index = np.clip(np.digitize(chi, edges) - 1, 0, HWP_BINS - 1)
    counts = np.bincount(index, minlength=HWP_BINS)
    sums = np.bincount(index, weights=r, minlength=HWP_BINS)
    profile = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    sigma = sigma_sample / np.sqrt(np.maximum(counts, 1))
    # Harmonics by least squares on the binned profile (weights = counts); averaging over a
    # bin of width w scales harmonic n by sinc(n w / 2 pi), which is divided out.
    centres = 0.5 * (edges[:-1] + edges[1:])
    seen = counts > 0
    columns = [np.ones(seen.sum())]
    for n in range(1, MAX_HARMONIC + 1):
        columns += [np.cos(n * centres[seen]), np.sin(n * centres[seen])]
    weights = np.sqrt(counts[seen])
    design = np.column_stack(columns) * weights[:, None]
    coefficients, *_ = np.linalg.lstsq(design, profile[seen] * weights, rcond=None)
    sigma_coefficient = sigma_sample * math.sqrt(2.0 / max(r.size, 1))
    harmonics = []
    for n in range(1, MAX_HARMONIC + 1):
        attenuation = np.sinc(n / HWP_BINS)
        a, b = coefficients[2 * n - 1] / attenuation, coefficients[2 * n] / attenuation
        amplitude = math.hypot(a, b)
        harmonics.append(
            Harmonic(
                detector=ctx.detector_names[k],
                n=n,
                amplitude_k=amplitude,
                sigma_k=sigma_coefficient,
                phase_rad=math.atan2(b, a),
                significance_sigma=amplitude / sigma_coefficient if sigma_coefficient > 0 else 0.0,
            )
        )
    return centres, profile, sigma, harmonics
