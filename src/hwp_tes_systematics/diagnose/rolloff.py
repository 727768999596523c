"""The detector time constant seen in the noise: a single pole rolls the noise off as
|H(f)|^2 = 1 / (1 + (2 pi f tau)^2).

The lines alone cannot tell tau: acting before the nonlinearity (as the TES's response to
the optical power does), it delays the 2f HWPSS by atan(2 pi 2 f_HWP tau), which the 2f
phase adjustment absorbs, and the nonlinearity's 4f line is made from that delayed 2f
line, so it lags by exactly twice as much; acting after it, the 4f lag differs from twice
the 2f lag only at third order in 2 pi f tau (2 x^3, x = 2 pi 2 f_HWP tau: 4e-4 rad at
5 ms and 1 Hz). The sky's lag (a shift of tau along the scan, 0.07 arcmin at 5 ms) is
below any pointing signature. What shows tau is the noise that passes through the same
pole: photon and phonon noise are optical or thermal power at the TES and are filtered
as the signal is; readout noise is not. Where the detector noise dominates, the white
level falls by 1 / (1 + (2 pi f tau)^2) towards Nyquist (at 31 Hz sampling and 5 ms, by
18 % at 15 Hz).

Fit (:func:`fit_rolloff`): per detector, the Whittle likelihood of the residual
periodogram on the noise fit's modes (above a few f_spin, off the HWP-harmonic lines),
the white + 1/f noise refitted jointly with u = tau^2 >= 0 (held at the noise fit's shape
the roll-off passes for a 1/f with a knee of ~1 Hz, which the white + 1/f fit then
reports):

    S(f) = N(f; net, f_knee, alpha) / (1 + (2 pi f)^2 u),
    -2 ln L = sum_f 2 [P_f / S(f) + ln S(f)],

against u = 0 with the noise refitted; Delta BIC = Delta(-2 ln L) + n_det ln N_eff. The roll-off is second order
in tau (Fisher: a 6 h pair at 31 Hz measures u to ~6e-7 s^2, tau ~2 ms at 5 sigma).
A readout or anti-aliasing filter rolls the noise off too: the report says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize

from .model import Context
from .noise import (
    NoiseModel,
    _narrow_bins,
    line_exclusion_mask,
    noise_psd,
    periodogram_scale,
    rolloff,
)
from .nominal import NOISE_FMIN_SPINS

V_MAX = 20.0  # bound of (2 pi f_Nyquist tau)^2: at 31 Hz, tau <= 23 ms


@dataclass
class RolloffFit:
    """tau per detector [s] (0 where none is seen) with its 1-sigma, and the likelihood gain."""

    tau_s: np.ndarray
    sigma_tau_s: np.ndarray
    delta_chi2: float  # Delta(-2 ln L) against no roll-off (<= 0)
    delta_bic: float
    band_hz: tuple[float, float]
    drop_at_nyquist: np.ndarray  # 1 - |H(f_s / 2)|^2 per detector
    noise: list  # NoiseModel per detector: white + 1/f through the fitted pole

    def as_dict(self) -> dict:
        return {
            "tau_s": self.tau_s.tolist(),
            "sigma_tau_s": self.sigma_tau_s.tolist(),
            "delta_chi2": self.delta_chi2,
            "delta_bic": self.delta_bic,
            "band_hz": list(self.band_hz),
        }


def fit_rolloff(ctx: Context, residual_f, noise, used: np.ndarray, ln_n_eff: float) -> RolloffFit:
    """The roll-off of each detector's noise (module docstring); ``residual_f`` the residual's
    rfft per detector, ``noise`` its noise models (the start of the noise's refit), ``used``
    the modes of the likelihood (the noise fit's: above NOISE_FMIN_SPINS f_spin, off lines)."""
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    used = used & ~line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * fs / n, 2e-4))
    used &= freqs > NOISE_FMIN_SPINS * ctx.f_spin_hz
    nyquist = fs / 2
    taus, sigmas, drops, models = [], [], [], []
    delta_chi2 = 0.0
    for k, model in enumerate(noise):
        power = np.asarray(residual_f[k])
        f, p_bin, m_bin = _narrow_bins(freqs, power.real**2 + power.imag**2, used)
        total = float(m_bin.sum())
        x = (f / nyquist) ** 2

        def objective(theta, f=f, p_bin=p_bin, m_bin=m_bin, total=total, x=x, model=model):
            """-2 ln L, the white level profiled; theta = (ln f_knee, alpha, v), v = (2 pi
            f_Nyq tau)^2."""
            g = _shape(theta, f, x, model)
            c = float(np.sum(p_bin / g)) / total
            return 2 * total * (1 + math.log(c)) + 2 * float(np.sum(m_bin * np.log(g)))

        bounds = [(math.log(1e-6), math.log(nyquist)), (0.05, 6.0), (0.0, V_MAX)]
        start = [math.log(max(model.fknee_hz, 1e-5)), float(np.clip(model.alpha, 0.05, 6.0))]
        without = scipy.optimize.minimize(
            lambda t: objective(np.append(t, 0.0)), start, method="L-BFGS-B", bounds=bounds[:2]
        )
        best = min(
            (
                scipy.optimize.minimize(
                    objective, [*without.x, v0], method="L-BFGS-B", bounds=bounds
                )
                for v0 in (0.02, 0.2, 1.0)
            ),
            key=lambda result: result.fun,
        )
        v = float(best.x[2]) if best.fun < without.fun else 0.0
        delta_chi2 += min(float(best.fun - without.fun), 0.0)
        # sigma of v from the curvature of -2 ln L along v (the others held)
        h = max(1e-3, 0.05 * v)
        around = [objective(np.array([*best.x[:2], max(v + d, 0.0)])) for d in (-h, 0.0, h)]
        curvature = (around[0] - 2 * around[1] + around[2]) / h**2
        sigma_v = math.sqrt(2.0 / curvature) if curvature > 0 else math.inf
        to_u = 1.0 / (2 * np.pi * nyquist) ** 2  # u = tau^2 = v / (2 pi f_Nyq)^2
        u, sigma_u = v * to_u, sigma_v * to_u
        tau = math.sqrt(u)
        c = float(np.sum(p_bin / _shape(best.x if v > 0 else [*without.x, 0.0], f, x, model)))
        scale = periodogram_scale(n, fs, float(np.mean(ctx.valid[k])))
        knee, slope = (best.x if v > 0 else without.x)[:2]
        models.append(
            NoiseModel(
                math.sqrt(c / total / scale), math.exp(knee), float(slope), model.fmin_hz, tau
            )
        )
        taus.append(tau)
        sigmas.append(sigma_u / (2 * tau) if tau > 0 else math.sqrt(sigma_u))
        drops.append(1.0 - float(rolloff(nyquist, u)))
    n_det = len(noise)
    return RolloffFit(
        tau_s=np.array(taus),
        sigma_tau_s=np.array(sigmas),
        delta_chi2=delta_chi2,
        delta_bic=delta_chi2 + n_det * ln_n_eff,
        band_hz=(NOISE_FMIN_SPINS * ctx.f_spin_hz, nyquist),
        drop_at_nyquist=np.array(drops),
        noise=models,
    )


def _shape(theta, f, x, model) -> np.ndarray:
    """The noise PSD per net^2 at f: theta = (ln f_knee, alpha, v), x = (f / f_Nyq)^2."""
    return noise_psd(f, 1.0, math.exp(theta[0]), theta[1], model.fmin_hz) / (1.0 + theta[2] * x)
