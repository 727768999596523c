"""Stochastic fluctuations of the 2f HWPSS amplitude: a gain (or HWP emission) that varies in
time as a random process, seen as broadband sidebands of the 2f line.

A relative gain g(t) with one-sided PSD P_g(f) multiplying the signal (dominated by the
HWPSS A_k cos(2 pi f_0 t + phi), f_0 = 2 f_HWP) adds to detector k's residual the power

    E_k(f) = (A_k^2 / 4) [P_g(|f - f_0|) + P_g(f + f_0)],   P_g(f) = a^2 (f_ref / f)^beta

[K^2/Hz], f_ref = 10 mHz, the offset clipped at the frequency resolution. (litebird_sim's
thermal gain drift has beta = alpha_drift and a = sqrt(2) sigma_drift (T_fluct / T_bath)
(fknee / f_ref)^(beta/2): its stream's one-sided PSD is twice its ``_get_psd``.) Its sky
and dipole sidebands are (D / A_k)^2 ~ 1e-4 of these and sit in the 1/f noise: a gain
fluctuation and an HWP emission fluctuation, which moves the HWPSS alone, are told apart
only when that part shows (:func:`dipole_signature`).

Fit (:func:`fit_fluctuations`): the Whittle likelihood of the residual periodogram,

    -2 ln L = sum_k sum_f [2 |R_kf|^2 / (S_kf + E_kf) + 2 ln(S_kf + E_kf)],

over the modes beyond INNER_HZ of 2 f_HWP and off the known lines, one (a, beta) for all
detectors (a common bath or HWP temperature) and each
detector's white + 1/f noise, refitted jointly (the excess would otherwise inflate the
white level); against the same noise refitted without E. Delta BIC = Delta(-2 ln L) +
k ln N_eff, k = 3 for a pair (a, beta, rho), 2 for one detector. When it is below the selection threshold, the noise of the selection becomes
S + E (:class:`WithExcess`) and the effects are selected again with these weights, so a
linear effect that only absorbed the fluctuation's slow part (a slow 2f modulation) must
earn its place again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize

from ..curvature import curvature_sigmas, marginal_sigmas
from ..fourier import rfft
from ..model import Context
from ..noise import (
    NoiseModel,
    independent_fraction,
    knee_bound_hz,
    line_exclusion_mask,
    noise_psd,
    noise_psd_log_gradient,
    periodogram_scale,
    rolloff,
)
from .coherence import CoherenceFit, fit_coherence
from .sideband_bins import sum_in_bins

F_REF_HZ = 0.01  # the frequency at which the gain PSD's amplitude a is quoted
# the likelihood leaves out the modes within this of 2 f_HWP: the deterministic effects
# (drifts, slow modulation, intensity coupling at 2 f_HWP +- f_spin) own that neighbourhood,
# the fluctuation claims only the broadband sidebands beyond it
INNER_HZ = 2e-3
SLOPE_BOUNDS = (0.0, 3.0)
# the second differences of the errors: (ln a, beta, rho), (ln NET, ln f_knee, alpha) per
# detector, and a pair's white correlation x
EXCESS_STEPS = (0.02, 0.02, 0.01)
NOISE_STEPS = (0.02, 0.02, 0.02)
X_STEP = 0.01


@dataclass(frozen=True)
class WithExcess:
    """A noise model plus an excess PSD tabulated on a frequency grid (``psd`` adds them)."""

    base: NoiseModel
    freqs_hz: np.ndarray
    excess_psd: np.ndarray

    def psd(self, freqs_hz) -> np.ndarray:
        f = np.abs(np.asarray(freqs_hz, dtype=float))
        return self.base.psd(f) + np.interp(f, self.freqs_hz, self.excess_psd)

    def __getattr__(self, name):  # net_k_sqrt_s, fknee_hz, alpha, fmin_hz of the base
        return getattr(self.base, name)


def gain_psd(offsets_hz: np.ndarray, amplitude: float, slope: float, resolution_hz: float):
    """P_g = a^2 (f_ref / f)^beta [1/Hz], the offset clipped at the resolution."""
    f = np.maximum(np.abs(offsets_hz), resolution_hz)
    return amplitude**2 * (F_REF_HZ / f) ** slope


def sideband_psd(freqs_hz, carrier_hz, amplitude_k, gain_amplitude, slope, resolution_hz):
    """E(f) = (A^2 / 4) [P_g(|f - f_0|) + P_g(f + f_0)] [K^2/Hz]."""
    return (amplitude_k**2 / 4) * (
        gain_psd(freqs_hz - carrier_hz, gain_amplitude, slope, resolution_hz)
        + gain_psd(freqs_hz + carrier_hz, gain_amplitude, slope, resolution_hz)
    )


@dataclass
class FluctuationFit:
    """The fitted fluctuation: (a, beta) with uncertainties, the likelihood gain, noise."""

    amplitude: float  # a [1/sqrt(Hz)] at F_REF_HZ
    slope: float
    correlation: float  # rho: 1 a gain common to the detectors, 0 independent ones
    sigma_amplitude: float
    sigma_slope: float
    sigma_correlation: float
    delta_chi2: float  # Delta(-2 ln L) against the noise alone (negative: better)
    delta_bic: float
    noise: list  # WithExcess per detector (the noise of the selection when selected)
    base_noise: list  # the white + 1/f models refitted with the excess
    carriers_k: np.ndarray  # A_k
    carrier_hz: float
    # three or more detectors: rho, and the groups it holds in (:mod:`.coherence`); None
    # for one detector or a pair (the pair's rho is fitted with the noise)
    coherence: CoherenceFit | None = None

    def rms(self, f_lo_hz: float, f_hi_hz: float) -> float:
        """sqrt(int P_g df) over [f_lo, f_hi]: the gain's rms fluctuation in that band."""
        power = 1.0 - self.slope
        if abs(power) < 1e-9:
            integral = math.log(f_hi_hz / f_lo_hz)
        else:
            integral = (f_hi_hz**power - f_lo_hz**power) / power
        return float(self.amplitude * math.sqrt(F_REF_HZ**self.slope * integral))


@dataclass
class IndependentSidebands:
    """-2 ln L of independent detectors' binned periodograms (one detector, or three and more
    in :func:`fit_fluctuations`) and its gradient in theta = (ln NET, ln f_knee, alpha per
    detector, ln a, beta, rho):

        -2 ln L = sum_k 2 sum_b [P_kb / T_kb + m_b ln T_kb],  T_k = S_k + x_k (L + U),

    S_k = c_kb noise_psd, L and U the gain's P_g(|f - f_0|) and P_g(f + f_0); the gradient is
    d(-2 ln L) / dT = 2 (m / T - P / T^2) times dS = S d ln S for detector k's noise
    parameters (:func:`.noise.noise_psd_log_gradient`), dT / d ln a = 2 x_k (L + U) and
    dT / d beta = x_k [L ln(f_ref / |f - f_0|) + U ln(f_ref / (f + f_0))]; rho does not
    enter (its derivative is 0)."""

    f_hz: np.ndarray  # (n_b,) the bins' mean frequencies
    modes: np.ndarray  # (n_b,) m_b, the modes summed in each bin
    power: np.ndarray  # (n_det, n_b) P_kb, the summed periodograms
    noise_factor: np.ndarray  # (n_det, n_b) c_kb, the periodogram scale times the held pole
    fmin_hz: np.ndarray  # (n_det,)
    sideband_factor: np.ndarray  # (n_det,) x_k = s_k A_k^2 / 4
    carrier_hz: float
    resolution_hz: float

    def __post_init__(self):
        self.n_det = self.power.shape[0]
        self.offsets = (self.f_hz - self.carrier_hz, self.f_hz + self.carrier_hz)
        self.ln_offsets = [
            np.log(F_REF_HZ / np.maximum(np.abs(offset), self.resolution_hz))
            for offset in self.offsets
        ]

    def __call__(self, theta, with_excess: bool) -> tuple[float, np.ndarray]:
        """(-2 ln L, its gradient) at theta; without the excess theta is the noise's alone."""
        n_noise = 3 * self.n_det
        log_net, log_fknee, alpha = np.asarray(theta[:n_noise]).reshape(self.n_det, 3).T
        noise, d_knee, d_alpha = noise_psd_log_gradient(
            self.f_hz, log_net, log_fknee, alpha, self.fmin_hz
        )
        noise *= self.noise_factor
        total = noise
        x = self.sideband_factor[:, None]
        if with_excess:
            gain = math.exp(theta[n_noise])
            lower, upper = (
                gain_psd(offset, gain, theta[n_noise + 1], self.resolution_hz)
                for offset in self.offsets
            )
            total = noise + x * (lower + upper)
        value = 2 * float(np.sum(self.power / total + self.modes * np.log(total)))
        d_total = 2 * (self.modes / total - self.power / total**2)
        d_noise = d_total * noise
        gradient = np.zeros(len(theta))
        gradient[0:n_noise:3] = 2 * d_noise.sum(axis=1)
        gradient[1:n_noise:3] = np.sum(d_noise * d_knee, axis=1)
        gradient[2:n_noise:3] = np.sum(d_noise * d_alpha, axis=1)
        if with_excess:
            d_excess = np.sum(d_total * x, axis=0)
            ln_lower, ln_upper = self.ln_offsets
            gradient[n_noise] = 2 * float(np.dot(d_excess, lower + upper))
            gradient[n_noise + 1] = float(np.dot(d_excess, lower * ln_lower + upper * ln_upper))
        return value, gradient


def carrier_phases(ctx: Context, carrier_hz: float) -> np.ndarray:
    """psi_k of each detector's 2f carrier cos(2 pi f_0 t + psi_k) in numpy's FFT convention
    (X_f0 = (n / 2) e^{i psi}), from the adjusted nominal HWPSS."""
    phase = np.exp(-2j * np.pi * carrier_hz * ctx.times_s)
    return np.angle(ctx.carrier @ phase)


def pair_determinant(noise, excess_scales, lower, upper, rho, d_psi):
    """det of the pair's 2 x 2 covariance per mode, [[N_A + E_A, C], [C*, N_B + E_B]],
    E_k = e_k (L + U), C = rho sqrt(e_A e_B) (L e^{i dpsi} + U e^{-i dpsi}), written as a
    sum of non-negative terms, N_A N_B + N_A E_B + E_A N_B + e_A e_B [(1 - rho^2) (L + U)^2
    + 2 rho^2 L U (1 - cos 2 dpsi)], so that it stays positive where the sidebands exceed
    the noise by many orders and rho = 1 (the difference E_A E_B - |C|^2 rounds to <= 0)."""
    both = lower + upper
    excess = [e * both for e in excess_scales]
    coherent = (1 - rho**2) * both**2 + 2 * rho**2 * lower * upper * (1 - math.cos(2 * d_psi))
    return (
        noise[0] * noise[1]
        + noise[0] * excess[1]
        + excess[0] * noise[1]
        + excess_scales[0] * excess_scales[1] * coherent
    )


def fit_fluctuations(
    ctx: Context,
    residual_f,
    noise: list[NoiseModel],
    used: np.ndarray,
    ln_n_eff: float,
    also_from: list[NoiseModel] | None = None,
    coherence_below: float | None = None,
) -> FluctuationFit:
    """Maximum-Whittle-likelihood (a, beta, rho) of the 2f sidebands with each detector's
    noise refitted alongside (module docstring); ``used`` the modes of the likelihood;
    ``also_from``: another noise to start both fits from (the recording's nominal noise:
    beside strong sidebands a shallow 1/f, alpha ~0.1 with its knee near 1 Hz, passes for
    part of the white level, a local optimum the fit can start in), the best kept.

    With two detectors the likelihood is the pair's: per mode the 2 x 2 covariance
    [[S_A + E_A, C], [C*, S_B + E_B]], C = rho sqrt(s_A s_B) (A_A A_B / 4) [P_g(|f - f_0|)
    e^{i dpsi} + P_g(f + f_0) e^{-i dpsi}] (dpsi the carriers' phase difference), and
    -2 ln L = sum_f 2 [ln det + R^H Sigma^-1 R]: a gain common to the detectors (rho = 1)
    makes their sidebands coherent while their noise is independent, which separates the
    sidebands' far wings from the white noise they would otherwise pass for. With three or
    more detectors they are fitted as independent, and, where Delta BIC is below
    ``coherence_below``, rho and the groups it holds in follow (:mod:`.coherence`).
    """
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    carrier = 2 * ctx.f_hwp_hz
    used = used & (np.abs(freqs - carrier) > INNER_HZ)
    used &= ~line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * fs / n, 2e-4))
    scales = [periodogram_scale(n, fs, float(np.mean(ctx.valid[k]))) for k in range(len(noise))]
    rows = [np.asarray(r)[used] for r in residual_f]
    n_det = len(rows)
    pair = n_det == 2
    # the periodograms summed in bins 1/2 % wide in f and in |f - f_0|, over which S, E and C
    # are constant to ~1e-2 of themselves (the likelihood then needs the sums only)
    f, counts, power, cross = sum_in_bins(
        freqs[used],
        carrier,
        [r.real**2 + r.imag**2 for r in rows],
        rows[0].conj() * rows[1] if pair else None,
    )
    resolution = fs / n
    carriers = np.asarray(ctx.a2_k, dtype=float)
    psi = carrier_phases(ctx, carrier)
    fmins = [m.fmin_hz for m in noise]
    poles = [rolloff(f, getattr(m, "tau_s", 0.0) ** 2) for m in noise]  # held
    # a pair's noise has a white correlation x too (crosstalk, :mod:`.crosstalk`), fitted
    # with and without the fluctuation: the pair's coherent sidebands are not credited
    # with a correlation a leak between the detectors makes at every frequency
    n_noise = 3 * n_det + (1 if pair else 0)

    def as_start(models):
        out = []
        for m in models:
            out += [math.log(m.net_k_sqrt_s), math.log(max(m.fknee_hz, 1e-5)), m.alpha]
        return np.array(out + ([0.0] if pair else []))

    start = as_start(noise)
    starts = [start] if also_from is None else [start, as_start(also_from)]
    knee_max_hz = knee_bound_hz(ctx.f_hwp_hz, fs)  # (see there: else the wings pass for 1/f)
    noise_bounds = []
    for k in range(n_det):
        noise_bounds += [
            (start[3 * k] - 5.0, start[3 * k] + 5.0),
            (math.log(1e-6), math.log(knee_max_hz)),
            (0.05, 6.0),
        ]
    if pair:
        noise_bounds.append((-0.5, 0.5))
    excess_bounds = [(math.log(1e-9), 0.0), SLOPE_BOUNDS, (0.0, 1.0)]

    excess_scales = [scales[k] * carriers[k] ** 2 / 4 for k in range(n_det)]  # A_k^2 / 4

    def noise_of(theta, k):
        """S_k, detector k's noise in the bins."""
        log_net, log_fknee, alpha = theta[3 * k : 3 * k + 3]
        return (
            scales[k] * noise_psd(f, math.exp(log_net), math.exp(log_fknee), alpha, fmins[k])
        ) * poles[k]

    def sidebands(theta):
        """P_g(|f - f_0|) and P_g(f + f_0) of the gain in theta's last three parameters."""
        log_a, slope, _ = theta[n_noise:]
        return (
            gain_psd(f - carrier, math.exp(log_a), slope, resolution),
            gain_psd(f + carrier, math.exp(log_a), slope, resolution),
        )

    def pair_spectra(theta, with_excess):
        """The pair's S_k + E_k per detector, cross term C + X (X = x sqrt(S_A S_B)) and
        determinant per bin."""
        total = [noise_of(theta, k) for k in range(n_det)]
        leak = theta[3 * n_det] * np.sqrt(total[0] * total[1])
        if not with_excess:
            return total, leak, total[0] * total[1] - leak**2
        rho = theta[n_noise + 2]
        lower, upper = sidebands(theta)
        d_psi = psi[0] - psi[1]
        c = (
            rho
            * math.sqrt(excess_scales[0] * excess_scales[1])
            * (lower * np.exp(1j * d_psi) + upper * np.exp(-1j * d_psi))
        )
        det = pair_determinant(total, excess_scales, lower, upper, rho, d_psi)
        det = det - 2 * (c.real * leak) - leak**2  # |C + X|^2
        for k in range(n_det):
            total[k] = total[k] + excess_scales[k] * (lower + upper)
        return total, c + leak, det

    def minus_two_ln_l(theta, with_excess: bool):
        if not pair:
            return independent_likelihood(theta, with_excess)[0]
        total, c, det = pair_spectra(theta, with_excess)
        det = np.maximum(det, 1e-12 * total[0] * total[1])  # (a far corner of x, rho)
        quadratic = (total[1] * power[0] + total[0] * power[1] - 2 * (c * cross).real) / det
        return 2 * float(np.sum(counts * np.log(det) + quadratic))

    # one detector or three and more: independent detectors
    independent_likelihood = IndependentSidebands(
        f,
        counts,
        np.array(power),
        np.array(scales)[:, None] * np.array(poles),
        np.array(fmins),
        np.array(excess_scales),
        carrier,
        resolution,
    )

    def minimise(x0, with_excess):
        bounds = noise_bounds + (excess_bounds if with_excess else [])
        x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])
        if pair:
            return scipy.optimize.minimize(
                minus_two_ln_l, x0, args=(with_excess,), method="L-BFGS-B", bounds=bounds
            )
        return scipy.optimize.minimize(
            independent_likelihood,
            x0,
            args=(with_excess,),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
        )

    without = min((minimise(x, False) for x in starts), key=lambda result: result.fun)
    # a coarse grid in (ln a, beta, rho) with the noise held, then everything jointly
    grid = [
        (minus_two_ln_l(np.concatenate([without.x, [log_a, slope, rho]]), True), log_a, slope, rho)
        for log_a in np.log(np.geomspace(1e-6, 1e-1, 16))
        for slope in (0.5, 1.0, 1.5, 2.0, 2.5)
        for rho in ((0.0, 0.5, 0.95) if pair else (0.0,))
    ]
    _, log_a, slope, rho = min(grid)
    # jointly from the noise alone's optimum and from the given noise (the noise alone,
    # made to take the sidebands, can sit in a corner, e.g. alpha at its bound)
    best = min(
        (
            minimise(np.concatenate([noise_x, [log_a, slope, rho]]), True)
            for noise_x in (without.x, *starts)
        ),
        key=lambda result: result.fun,
    )
    # the noise alone again from the joint fit's noise: a gain must not be credited with
    # what a better-converged noise fit gives
    again = minimise(best.x[:n_noise], False)
    # v: the independent modes per mode of the pair's gapped periodograms (noise module)
    independent = float(np.mean([independent_fraction(valid) for valid in ctx.valid]))
    delta_chi2 = independent * float(best.fun - min(without.fun, again.fun))
    # errors of (ln a, beta, rho): the conditional curvature of each, then, where the
    # Hessian is positive definite, marginal over each other and, for one detector or a
    # pair, over the noise and the pair's x too (a gain's far wings trade with the white
    # level and the 1/f, rho with x); with more detectors the noise is held (3 n_det more
    # parameters), and rho's error is the coherence fit's (below)
    sigmas = curvature_sigmas(
        lambda p: independent * minus_two_ln_l(np.concatenate([best.x[:n_noise], p]), True),
        best.x[n_noise:],
        steps=EXCESS_STEPS,
        bounds=excess_bounds,
    )
    if n_det <= 2:
        free = n_noise + (3 if pair else 2)  # one detector's likelihood has no rho
        rest = best.x[free:]
        marginal = marginal_sigmas(
            lambda p: independent * minus_two_ln_l(np.concatenate([p, rest]), True),
            best.x[:free],
            steps=NOISE_STEPS * n_det
            + ((X_STEP,) if pair else ())
            + EXCESS_STEPS[: free - n_noise],
            bounds=(noise_bounds + excess_bounds)[:free],
        )[n_noise:]
    else:
        head, rest = best.x[:n_noise], best.x[n_noise + 2 :]
        marginal = marginal_sigmas(
            lambda p: independent * minus_two_ln_l(np.concatenate([head, p, rest]), True),
            best.x[n_noise : n_noise + 2],
            steps=EXCESS_STEPS[:2],
            bounds=excess_bounds[:2],
        )
    sigmas[: len(marginal)] = marginal
    amplitude, slope, rho = (
        math.exp(best.x[n_noise]),
        float(best.x[n_noise + 1]),
        float(best.x[n_noise + 2]),
    )
    base, with_excess = [], []
    for k in range(n_det):
        log_net, log_fknee, alpha = best.x[3 * k : 3 * k + 3]
        model = NoiseModel(
            math.exp(log_net), math.exp(log_fknee), float(alpha), fmins[k], noise[k].tau_s
        )
        base.append(model)
        excess = sideband_psd(freqs, carrier, carriers[k], amplitude, slope, resolution)
        with_excess.append(WithExcess(model, freqs, excess))
    coherence = None
    delta_bic = delta_chi2 + (3 if pair else 2) * ln_n_eff
    if n_det > 2 and coherence_below is not None and delta_bic < coherence_below:
        coherence = fit_coherence(
            ctx,
            rows,
            freqs[used],
            carrier,
            [scales[k] * base[k].psd(freqs[used]) for k in range(n_det)],
            [scales[k] * carriers[k] ** 2 / 4 for k in range(n_det)],
            psi,
            amplitude,
            slope,
            resolution,
            independent,
        )
        rho, sigmas[2] = coherence.correlation, coherence.sigma_correlation
    return FluctuationFit(
        amplitude=amplitude,
        slope=slope,
        correlation=rho,
        sigma_amplitude=amplitude * sigmas[0],
        sigma_slope=sigmas[1],
        sigma_correlation=sigmas[2],
        coherence=coherence,
        # the pair's likelihood counts rho: three parameters (two for one detector)
        delta_chi2=delta_chi2,
        delta_bic=delta_bic,
        noise=with_excess,
        base_noise=base,
        carriers_k=carriers,
        carrier_hz=carrier,
    )


def dipole_signature(ctx: Context, fit: FluctuationFit, noise) -> float:
    """The Delta(-2 ln L) a gain fluctuation's dipole and sky sidebands would add, from the
    fitted P_g and the nominal sky + dipole spectrum (what would tell a gain fluctuation from
    an HWP emission one): sum_f E_D(f)^2 / S(f)^2 over the modes, E_D = (f_s / 2 n) x
    sum_f' P_g(|f - f'|) |D_f'|^2 restricted to the strongest sky + dipole modes."""
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    resolution = fs / n
    total = 0.0
    for k in range(ctx.n_detectors):
        spectrum = rfft(ctx.sky[k] + ctx.dipole[k] - np.mean(ctx.dipole[k]))
        power = spectrum.real**2 + spectrum.imag**2
        strongest = np.argsort(power)[-64:]
        excess = np.zeros(freqs.size)
        for j in strongest:
            excess += power[j] * (
                gain_psd(freqs - freqs[j], fit.amplitude, fit.slope, resolution)
                + gain_psd(freqs + freqs[j], fit.amplitude, fit.slope, resolution)
            )
        excess *= fs / (2 * n)
        s = periodogram_scale(n, fs, float(np.mean(ctx.valid[k]))) * noise[k].psd(freqs)
        total += float(np.sum((excess[1:] / s[1:]) ** 2))
    return total
