"""Step 2 of the diagnosis: the four searches on the residual, as a :class:`Mismatch`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.fft

from ..effects.glitches import GlitchEvent, find_transients
from ..fourier import rfft
from ..model import Context
from ..noise import (
    NoiseModel,
    fitted_modes,
    independent_fraction,
    line_exclusion_mask,
    periodogram_scale,
)
from .drifts import dc_offset, drifts
from .frequency import Line, excess_bands, find_lines
from .hwp_angle import Harmonic, hwp_profile
from .sky import sky_residual


@dataclass
class Mismatch:
    """Where the recording and the simulation differ (all detectors)."""

    lines: list[Line] = field(default_factory=list)
    excess_bands: list[dict] = field(default_factory=list)
    harmonics: list[Harmonic] = field(default_factory=list)
    profiles: dict = field(default_factory=dict)  # detector -> (centres, profile, sigma)
    transients: list[GlitchEvent] = field(default_factory=list)
    drifts: list[dict] = field(default_factory=list)
    dc_offsets: dict = field(default_factory=dict)  # detector -> (mean, sigma)
    sky: dict = field(default_factory=dict)

    def significant_harmonics(self, min_sigma: float = 5.0) -> list[Harmonic]:
        return [h for h in self.harmonics if h.significance_sigma > min_sigma]

    def as_dict(self) -> dict:
        sky = {k: v for k, v in self.sky.items() if k not in ("residual_map", "hits")}
        return {
            "lines": [line.as_dict() for line in self.lines],
            "excess_bands": self.excess_bands,
            "harmonics": [h.as_dict() for h in self.harmonics],
            "transients": [asdict(e) for e in self.transients],
            "drifts": self.drifts,
            "dc_offsets": {
                k: {"mean_k": v[0], "sigma_k": v[1]} for k, v in self.dc_offsets.items()
            },
            "sky": sky,
        }


def locate(
    ctx: Context,
    residual: np.ndarray,
    noise_models: list[NoiseModel],
    nominal_noise: list[NoiseModel],
    workers: int = 1,
    residual_f: np.ndarray | None = None,
) -> Mismatch:
    """Run the four searches on the residual (n_det, n); ``noise_models`` from the residual;
    ``residual_f`` its rfft (flagged samples zeroed) if the caller has it."""
    mismatch = Mismatch()
    n = ctx.n_samples
    fs = ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    residual = np.where(ctx.valid, residual, 0.0)
    if residual_f is None:
        residual_f = rfft(residual, axis=-1, workers=workers)
    modes = fitted_modes(n)
    lines_mask = line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * fs / n, 2e-4))
    sigma_samples = []
    for k, name in enumerate(ctx.detector_names):
        noise = noise_models[k]
        scale = periodogram_scale(n, fs, float(ctx.valid[k].mean()))
        s_est = scale * noise.psd(freqs)
        s_nom = scale * nominal_noise[k].psd(freqs)
        sigma_sample = noise.net_k_sqrt_s * math.sqrt(fs)
        sigma_samples.append(sigma_sample)
        mismatch.lines += find_lines(residual[k], ctx, k, noise)
        mismatch.excess_bands += excess_bands(
            residual_f[k],
            freqs,
            s_nom,
            modes & ~lines_mask,
            name,
            valid_fraction=independent_fraction(ctx.valid[k]),
        )
        centres, profile, sigma, harmonics = hwp_profile(residual[k], ctx, k, sigma_sample)
        mismatch.profiles[name] = (centres, profile, sigma)
        mismatch.harmonics += harmonics
        mismatch.transients += find_transients(
            residual_f[k], s_est, ctx.valid[k], ctx.times_s, scale, k, workers=workers
        )
        weights = np.zeros(freqs.size)
        weights[modes] = 1.0 / s_est[modes]
        mismatch.drifts += drifts(residual_f[k], ctx, k, weights, workers)
        mismatch.dc_offsets[name] = dc_offset(residual[k], ctx.valid[k], noise, ctx.duration_s)
    mismatch.sky = sky_residual(residual, ctx, np.array(sigma_samples))
    return mismatch
