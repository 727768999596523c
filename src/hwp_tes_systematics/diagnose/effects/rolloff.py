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

against u = 0 with the noise refitted (from its own start and from the joint fit's
noise, the better kept: the pole is not credited with a better-converged noise fit); a
fitted gain fluctuation's sidebands E(f) are held in S = N / (1 + ...) + E, the white
level then a free parameter, since their wings fall away from 2 f_HWP as a roll-off does
(:mod:`.fluctuations`); Delta BIC = Delta(-2 ln L) + n_det ln N_eff. The roll-off is second order
in tau (Fisher: a 6 h pair at 31 Hz measures u to ~6e-7 s^2, tau ~2 ms at 5 sigma).
A readout or anti-aliasing filter rolls the noise off too: the report says so.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize

from ..model import Context
from ..noise import (
    NOISE_FMIN_SPINS,
    NoiseModel,
    _narrow_bins,
    independent_fraction,
    knee_bound_hz,
    line_exclusion_mask,
    noise_psd,
    periodogram_scale,
    rolloff,
)

V_MAX = 20.0  # bound of (2 pi f_Nyquist tau)^2: at 31 Hz, tau <= 46 ms


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
    noise_without: list  # the same refitted with no pole (tau = 0)

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
    taus, sigmas, drops, models, models_without = [], [], [], [], []
    delta_chi2 = 0.0
    for k, model in enumerate(noise):
        power = np.asarray(residual_f[k])
        f, p_bin, m_bin = _narrow_bins(freqs, power.real**2 + power.imag**2, used)
        total = float(m_bin.sum())
        x = (f / nyquist) ** 2
        scale = periodogram_scale(n, fs, float(np.mean(ctx.valid[k])))
        # a fitted gain fluctuation's sidebands (fluctuations.WithExcess), held: they fall
        # with the offset from 2 f_HWP and would otherwise pass for a roll-off
        excess = (
            scale * np.interp(f, model.freqs_hz, model.excess_psd)
            if hasattr(model, "excess_psd")
            else None
        )
        base = getattr(model, "base", model)

        def objective(theta, f=f, p_bin=p_bin, m_bin=m_bin, total=total, x=x, e=excess, base=base):
            """-2 ln L; theta = (ln f_knee, alpha, v, ln c), v = (2 pi f_Nyq tau)^2, c the
            white level (profiled without an excess, then theta[3] is unused)."""
            g = _shape(theta, f, x, base)
            if e is None:
                c = float(np.sum(p_bin / g)) / total
                return 2 * total * (1 + math.log(c)) + 2 * float(np.sum(m_bin * np.log(g)))
            s = math.exp(theta[3]) * g + e  # the expected periodogram of a mode
            return 2 * float(np.sum(p_bin / s + m_bin * np.log(s)))

        # beside a held excess the knee stays below f_HWP (noise.knee_bound_hz); without
        # one a shallow 1/f up to Nyquist is the noise model's only room for a broadband
        # excess of unknown shape, and a roll-off must beat it
        knee_max_hz = nyquist if excess is None else knee_bound_hz(ctx.f_hwp_hz, fs)
        knee = (math.log(1e-6), math.log(knee_max_hz))
        start = [
            float(np.clip(math.log(max(base.fknee_hz, 1e-5)), *knee)),
            float(np.clip(base.alpha, 0.05, 6.0)),
        ]
        level = math.log(scale * base.net_k_sqrt_s**2)  # c of S = c g (g: noise_psd at net 1)
        bounds = [knee, (0.05, 6.0), (0.0, V_MAX), (level - 5.0, level + 5.0)]

        def fit(x0, with_pole, objective=objective, bounds=bounds, excess=excess):
            """Minimise over (ln f_knee, alpha, [v,] [ln c]): v held at 0 without the pole,
            ln c only beside an excess (profiled otherwise)."""
            free = [0, 1] + ([2] if with_pole else []) + ([3] if excess is not None else [])

            def partial(t):
                theta = np.array([x0[0], x0[1], 0.0, x0[3]])
                theta[free] = t
                return objective(theta)

            result = scipy.optimize.minimize(
                partial,
                np.asarray(x0)[free],
                method="L-BFGS-B",
                bounds=[bounds[i] for i in free],
            )
            theta = np.array([x0[0], x0[1], 0.0, x0[3]])
            theta[free] = result.x
            return theta, float(result.fun)

        without_x, without_fun = fit([*start, 0.0, level], False)
        best_x, best_fun = min(
            (fit([*without_x[:2], v0, without_x[3]], True) for v0 in (0.02, 0.2, 1.0)),
            key=lambda trial: trial[1],
        )
        # the noise alone again from the joint fit's noise: the pole must not be credited
        # with what a better-converged noise fit gives
        again_x, again_fun = fit([*best_x[:2], 0.0, best_x[3]], False)
        if again_fun < without_fun:
            without_x, without_fun = again_x, again_fun
        v = float(best_x[2]) if best_fun < without_fun else 0.0
        independent = independent_fraction(ctx.valid[k])  # v: a gapped periodogram's modes
        delta_chi2 += independent * min(best_fun - without_fun, 0.0)
        chosen = best_x if v > 0 else without_x
        # sigma of v from the curvature of -2 ln L along v (the others held)
        h = max(1e-3, 0.05 * v)
        around = [
            objective(np.array([*chosen[:2], max(v + d, 0.0), chosen[3]])) for d in (-h, 0.0, h)
        ]
        curvature = independent * (around[0] - 2 * around[1] + around[2]) / h**2
        sigma_v = math.sqrt(2.0 / curvature) if curvature > 0 else math.inf
        to_u = 1.0 / (2 * np.pi * nyquist) ** 2  # u = tau^2 = v / (2 pi f_Nyq)^2
        u, sigma_u = v * to_u, sigma_v * to_u
        tau = math.sqrt(u)
        if excess is None:
            c = float(np.sum(p_bin / _shape(chosen, f, x, base))) / total
        else:
            c = math.exp(chosen[3])
        c_without = (
            float(np.sum(p_bin / _shape(without_x, f, x, base))) / total
            if excess is None
            else math.exp(without_x[3])
        )
        for theta, level_c, tau_k, out in (
            (chosen, c, tau, models),
            (without_x, c_without, 0.0, models_without),
        ):
            fitted = NoiseModel(
                math.sqrt(level_c / scale),
                math.exp(theta[0]),
                float(theta[1]),
                base.fmin_hz,
                tau_k,
            )
            # a held excess stays in the model (fluctuations.WithExcess around the new base)
            out.append(fitted if excess is None else dataclasses.replace(model, base=fitted))
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
        noise_without=models_without,
    )


def _shape(theta, f, x, model) -> np.ndarray:
    """The noise PSD per net^2 at f: theta = (ln f_knee, alpha, v), x = (f / f_Nyq)^2."""
    return noise_psd(f, 1.0, math.exp(theta[0]), theta[1], model.fmin_hz) / (1.0 + theta[2] * x)
