"""Measurements on the residual of one effect, for the evidence each effect states in words.

``Evidence`` holds the residual minus the fitted models of the OTHER selected effects
(what the data show of one effect alone) and measures on it: lines at given frequencies,
harmonics in the HWP angle, the DC shift, the 2f and dipole drifts (:mod:`.locate`) and
the 2 f_HWP +- f_spin lines, with the fitted noise. The sentence itself is written by the
effect (``Effect.evidence`` in :mod:`.effects`), next to its forward model.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

from ..fourier import rfft
from ..locate import dc_offset, drifts, hwp_profile, line_at
from ..noise import independent_fraction, periodogram_scale


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
            v = independent_fraction(ctx.valid[k])  # scales the periodogram, weights the modes
            s = periodogram_scale(ctx.n_samples, ctx.sampling_rate_hz, v) * self.noise[k].psd(freqs)
            weights = np.zeros(freqs.size)
            weights[1:-1] = v / s[1:-1]  # noise module
            residual_f = rfft(self.residual[k], workers=self.workers)
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
