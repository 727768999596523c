"""Noise of the residual: white + 1/f model, a robust estimate, and the Whittle likelihood.

Model (litebird_sim's "toast" 1/f model, one-sided PSD in K^2/Hz):

    P(f) = 2 w^2 (f^alpha + fk^alpha) / (f^alpha + fmin^alpha),

w the white level (NET) in K sqrt(s) (sigma per sample = w sqrt(f_s)), fk the knee
frequency, alpha the slope and fmin the frequency below which the spectrum flattens
(kept at its configured value).

Robust estimate (:func:`estimate_noise`): Welch PSD with MEDIAN averaging over Hann
segments with no invalid sample (a line or a transient in a few segments does not pull it;
a segment cut by a gap would: the gap's edges cut the residual's lines and offset, whose
leakage fills the band), frequencies near
the known lines (n f_HWP +- m f_spin, n <= 8, |m| <= 3) excluded, averaged in
logarithmic frequency bins and fitted in log space, ln P(f_b) against ln P-hat_b with
weights m_b (the number of Welch bins averaged); the uncertainties are the
least-squares covariance scaled by the reduced chi^2.

Whittle likelihood (the fit's noise model, :func:`whittle_fit`): for the rfft R_f of n
samples of which a fraction v is valid, E|R_f|^2 = S_f = P(f) n f_s v / 2 and

    -2 ln L = v sum_f [ 2 |R_f - M_f|^2 / S_f + 2 ln S_f ]  (+ const),

each complex mode counting two real degrees of freedom, times v: a gap correlates
neighbouring modes (the squared correlations of one mode with all others sum to 1 / v,
Parseval on the mask's spectrum), so n modes hold n v independent ones
(:func:`independent_fraction`); for white noise v sum_f |R_f|^2 / S_f is the time-domain
chi^2 over the valid samples, and a gap costs the precision it should. Weighting the Fourier
coefficients by 1/S_f is the prewhitening operator of the template fit. The
noise parameters are fitted by maximising L on the residual periodogram (line bins
excluded), with the periodogram summed in narrow frequency bins (1/2 % wide) over which
P is constant to better than 1e-3; their covariance is the inverse Fisher matrix
F_ij = sum_f d ln S_f / d theta_i  d ln S_f / d theta_j.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.signal


@dataclass(frozen=True)
class NoiseModel:
    """P(f) = 2 net^2 (f^alpha + fknee^alpha) / (f^alpha + fmin^alpha) / (1 + (2 pi f tau)^2)
    [K^2/Hz]: white + 1/f, through the detector's pole tau (0: none; :mod:`.rolloff`)."""

    net_k_sqrt_s: float
    fknee_hz: float
    alpha: float
    fmin_hz: float
    tau_s: float = 0.0

    def psd(self, freqs_hz) -> np.ndarray:
        psd = noise_psd(freqs_hz, self.net_k_sqrt_s, self.fknee_hz, self.alpha, self.fmin_hz)
        return psd * rolloff(freqs_hz, self.tau_s**2) if self.tau_s else psd

    @classmethod
    def from_detector(cls, detector: dict) -> NoiseModel:
        """From litebird_sim detector fields net_ukrts, fknee_mhz, alpha, fmin_hz."""
        return cls(
            net_k_sqrt_s=float(detector["net_ukrts"]) * 1e-6,
            fknee_hz=float(detector.get("fknee_mhz", 0.0)) * 1e-3,
            alpha=float(detector.get("alpha", 1.0)),
            fmin_hz=float(detector.get("fmin_hz", 1e-5)),
        )


def noise_psd(freqs_hz, net_k_sqrt_s, fknee_hz, alpha, fmin_hz) -> np.ndarray:
    """One-sided PSD [K^2/Hz] of the white + 1/f model (see the module docstring)."""
    f_alpha = np.power(np.abs(np.asarray(freqs_hz, dtype=float)), alpha)
    return (
        2.0
        * net_k_sqrt_s**2
        * (f_alpha + max(fknee_hz, 0.0) ** alpha)
        / (f_alpha + max(fmin_hz, 1e-30) ** alpha)
    )


def noise_psd_log_gradient(freqs_hz, log_net, log_fknee, alpha, fmin_hz):
    """:func:`noise_psd` of several detectors at once and its logarithmic derivatives, for
    the fits that take a gradient: from (n_det,) arrays of ln NET, ln f_knee, alpha and
    f_min, on positive frequencies (n_f,), S (n_det, n_f) and (d ln S / d ln f_knee,
    d ln S / d alpha), d ln S / d ln NET being 2:

        d ln S / d ln f_k = alpha f_k^alpha / (f^alpha + f_k^alpha),
        d ln S / d alpha = (f^alpha ln f + f_k^alpha ln f_k) / (f^alpha + f_k^alpha)
                         - (f^alpha ln f + f_min^alpha ln f_min) / (f^alpha + f_min^alpha).
    """
    ln_f = np.log(np.asarray(freqs_hz, dtype=float))[None, :]
    alpha = np.asarray(alpha, dtype=float)[:, None]
    ln_knee = np.asarray(log_fknee, dtype=float)[:, None]
    ln_min = np.log(np.maximum(np.asarray(fmin_hz, dtype=float), 1e-30))[:, None]
    f_alpha, knee_alpha, min_alpha = (np.exp(alpha * x) for x in (ln_f, ln_knee, ln_min))
    upper, lower = f_alpha + knee_alpha, f_alpha + min_alpha
    psd = 2.0 * np.exp(2.0 * np.asarray(log_net, dtype=float))[:, None] * upper / lower
    d_knee = alpha * knee_alpha / upper
    d_alpha = (f_alpha * ln_f + knee_alpha * ln_knee) / upper - (
        f_alpha * ln_f + min_alpha * ln_min
    ) / lower
    return psd, d_knee, d_alpha


def rolloff(freqs_hz, tau_squared_s2) -> np.ndarray:
    """|H(f)|^2 = 1 / (1 + (2 pi f)^2 tau^2) of a single pole."""
    return 1.0 / (1.0 + (2 * np.pi * np.asarray(freqs_hz, dtype=float)) ** 2 * tau_squared_s2)


def periodogram_scale(n_samples: int, sampling_rate_hz: float, valid_fraction: float) -> float:
    """S_f / P(f) = n f_s v / 2 for numpy's unnormalised rfft."""
    return 0.5 * n_samples * sampling_rate_hz * valid_fraction


def independent_fraction(valid) -> float:
    """v, the fraction of valid samples: the independent modes per mode of a gapped
    periodogram (module docstring); every -2 ln L summed over modes is weighted by it."""
    return float(np.mean(valid)) if valid is not None else 1.0


def fitted_modes(n_samples: int) -> np.ndarray:
    """The rfft modes the likelihood uses (bool, n_samples // 2 + 1): all but DC and, for
    an even length, the Nyquist mode (both real: one degree of freedom, not two)."""
    modes = np.ones(n_samples // 2 + 1, dtype=bool)
    modes[0] = False
    if n_samples % 2 == 0:
        modes[-1] = False
    return modes


def knee_bound_hz(f_hwp_hz: float, sampling_rate_hz: float) -> float:
    """The highest 1/f knee a noise refit beside an effect's excess may take: f_HWP
    (Nyquist without a HWP). A TES behind a spinning HWP whose 1/f reached f_HWP would not
    modulate the signal out of it; above it a shallow 1/f with its knee at Nyquist passes
    for a roll-off or for the far wings of a gain fluctuation's sidebands, and leaves the
    1/f below 10 mHz unfitted."""
    nyquist = sampling_rate_hz / 2
    return min(f_hwp_hz, nyquist) if f_hwp_hz > 0 else nyquist


def line_exclusion_mask(
    freqs_hz: np.ndarray,
    f_hwp_hz: float,
    f_spin_hz: float,
    half_width_hz: float,
    max_harmonic: int = 8,
    max_spin: int = 3,
) -> np.ndarray:
    """True at frequencies within ``half_width_hz`` of n f_HWP + m f_spin (n <= 8, |m| <= 3)."""
    near = np.zeros(freqs_hz.shape, dtype=bool)
    if f_hwp_hz <= 0:
        return near
    for n in range(1, max_harmonic + 1):
        for m in range(-max_spin, max_spin + 1):
            center = n * f_hwp_hz + m * f_spin_hz
            lo, hi = np.searchsorted(freqs_hz, [center - half_width_hz, center + half_width_hz])
            near[lo:hi] = True
    return near


@dataclass
class NoiseEstimate:
    """Noise parameters with uncertainties, and the spectrum they were fitted to."""

    model: NoiseModel
    sigma_net_k_sqrt_s: float
    sigma_fknee_hz: float
    sigma_alpha: float
    freqs_hz: np.ndarray = field(repr=False)
    psd: np.ndarray = field(repr=False)  # Welch (median) PSD of the residual [K^2/Hz]
    used: np.ndarray = field(repr=False)  # frequencies used in the fit

    def as_dict(self) -> dict:
        return {
            "net_k_sqrt_s": self.model.net_k_sqrt_s,
            "sigma_net_k_sqrt_s": self.sigma_net_k_sqrt_s,
            "fknee_hz": self.model.fknee_hz,
            "sigma_fknee_hz": self.sigma_fknee_hz,
            "alpha": self.model.alpha,
            "sigma_alpha": self.sigma_alpha,
            "fmin_hz": self.model.fmin_hz,
        }


def welch_segment(n_samples: int) -> int:
    """Welch segment: a power of two, about n / 8 (at least 256 samples)."""
    return int(max(256, 2 ** math.floor(math.log2(max(n_samples // 8, 256)))))


NOISE_FMIN_SPINS = 2.0  # the noise is fitted above 2 f_spin (extrapolated below)
MIN_WELCH_SEGMENTS = 5  # whole valid segments the median is taken over (fewer: shorter segments)


def median_bias(n_segments: int) -> float:
    """E[median] / E[mean] of n exponential variates (a periodogram bin's distribution):
    1 + sum_{i=1}^{(n-1)//2} (1/(2i+1) - 1/(2i)), the factor scipy's median Welch divides by."""
    i = 2 * np.arange(1, (n_segments - 1) // 2 + 1)
    return float(1 + np.sum(1.0 / (i + 1) - 1.0 / i))


def valid_welch(
    residual: np.ndarray, sampling_rate_hz: float, valid: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, int]:
    """Median Welch PSD [K^2/Hz] over the Hann segments (half overlap) with no invalid sample:
    (freqs, psd, segment). The segment is about n / 8 samples, halved until at least
    MIN_WELCH_SEGMENTS whole segments are valid (down to 256 samples); if none is, every
    segment is used."""
    n = residual.size
    segment = min(welch_segment(n), n)
    # invalid samples before each index: a segment [a, a + L) is whole if the count is equal
    invalid_before = None
    if valid is not None:
        invalid_before = np.concatenate([[0], np.cumsum(~np.asarray(valid, dtype=bool))])
    while True:
        starts = np.arange(0, n - segment + 1, segment // 2)
        if invalid_before is None:
            whole = np.ones(starts.size, dtype=bool)
        else:
            whole = invalid_before[starts + segment] == invalid_before[starts]
        if whole.sum() >= min(MIN_WELCH_SEGMENTS, starts.size) or segment <= 256:
            break
        segment //= 2
    if not whole.any():
        whole[:] = True
    freqs, _, power = scipy.signal.spectrogram(
        residual,
        fs=sampling_rate_hz,
        window="hann",
        nperseg=segment,
        noverlap=segment // 2,
        detrend="constant",
        scaling="density",
        mode="psd",
    )
    used = whole[: power.shape[1]]
    psd = np.median(power[:, used], axis=1) / median_bias(int(used.sum()))
    return freqs, psd, segment


def _log_bins(freqs, values, weights, per_decade=40):
    positive = freqs > 0
    freqs, values, weights = freqs[positive], values[positive], weights[positive]
    if freqs.size == 0:
        return freqs, values, weights
    edges = np.logspace(
        np.log10(freqs.min()) - 1e-9,
        np.log10(freqs.max()) + 1e-9,
        max(2, int(per_decade * np.log10(freqs.max() / freqs.min())) + 2),
    )
    index = np.digitize(freqs, edges)
    count = np.bincount(index, weights=weights, minlength=edges.size + 1)
    mean_f = np.bincount(index, weights=weights * freqs, minlength=edges.size + 1)
    mean_v = np.bincount(index, weights=weights * values, minlength=edges.size + 1)
    keep = count > 0
    return mean_f[keep] / count[keep], mean_v[keep] / count[keep], count[keep]


def estimate_noise(
    residual: np.ndarray,
    sampling_rate_hz: float,
    valid: np.ndarray | None = None,
    f_hwp_hz: float = 0.0,
    f_spin_hz: float = 0.0,
    fmin_hz: float = 1e-5,
    start: NoiseModel | None = None,
) -> NoiseEstimate:
    """Robust white + 1/f fit to the Welch (median) PSD of one detector's residual."""
    residual = np.asarray(residual, dtype=float)
    freqs, psd, segment = valid_welch(residual, sampling_rate_hz, valid)
    resolution = sampling_rate_hz / segment
    exclude = line_exclusion_mask(freqs, f_hwp_hz, f_spin_hz, 3 * resolution)
    used = (freqs > 1.5 * resolution) & (freqs < 0.98 * sampling_rate_hz / 2) & ~exclude
    used &= psd > 0
    f_bin, p_bin, m_bin = _log_bins(freqs[used], psd[used], np.ones(used.sum()))
    if start is None:
        high = freqs > 0.25 * sampling_rate_hz / 2
        white = float(np.median(psd[used & high])) if np.any(used & high) else float(np.median(psd))
        start = NoiseModel(math.sqrt(max(white, 1e-300) / 2), 0.02, 1.0, fmin_hz)
    fmin = start.fmin_hz if start.fmin_hz > 0 else fmin_hz

    def residuals(theta):
        log_net, log_fknee, alpha = theta
        model = noise_psd(f_bin, math.exp(log_net), math.exp(log_fknee), alpha, fmin)
        return np.sqrt(m_bin) * (np.log(p_bin) - np.log(model))

    x0 = np.array([math.log(start.net_k_sqrt_s), math.log(max(start.fknee_hz, 1e-5)), start.alpha])
    lower = [-np.inf, math.log(1e-6), 0.05]
    upper = [np.inf, math.log(sampling_rate_hz / 2), 6.0]
    x0 = np.clip(x0, np.array(lower) + 1e-9, np.array(upper) - 1e-9)
    solution = scipy.optimize.least_squares(residuals, x0, bounds=(lower, upper))
    dof = max(f_bin.size - 3, 1)
    scale = float(np.sum(solution.fun**2) / dof)
    try:
        cov = np.linalg.inv(solution.jac.T @ solution.jac) * scale
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    log_net, log_fknee, alpha = solution.x
    model = NoiseModel(math.exp(log_net), math.exp(log_fknee), float(alpha), fmin)
    variances = np.clip(np.diag(cov), 0, np.inf)
    return NoiseEstimate(
        model=model,
        sigma_net_k_sqrt_s=model.net_k_sqrt_s * math.sqrt(variances[0]),
        sigma_fknee_hz=model.fknee_hz * math.sqrt(variances[1]),
        sigma_alpha=math.sqrt(variances[2]),
        freqs_hz=freqs,
        psd=psd,
        used=used,
    )


@dataclass
class WhittleFit:
    model: NoiseModel
    covariance: np.ndarray  # of (ln net, ln fknee, alpha)

    @property
    def sigmas(self) -> tuple[float, float, float]:
        v = np.clip(np.diag(self.covariance), 0, np.inf)
        return (
            self.model.net_k_sqrt_s * math.sqrt(v[0]),
            self.model.fknee_hz * math.sqrt(v[1]),
            math.sqrt(v[2]),
        )


def _narrow_bins(freqs, power, use, relative_width=0.005):
    """Sum the periodogram over bins of relative width 1/2 % (>= 1 mode)."""
    f = freqs[use]
    p = power[use]
    if f.size == 0:
        return f, p, p
    # bin index: modes closer than relative_width * f share a bin
    log_f = np.log(np.maximum(f, f[f > 0].min() if np.any(f > 0) else 1.0))
    index = np.floor(log_f / relative_width).astype(np.int64)
    index -= index.min()
    # distinct consecutive indices -> bins
    boundaries = np.flatnonzero(np.diff(index)) + 1
    starts = np.concatenate([[0], boundaries])
    counts = np.diff(np.concatenate([starts, [f.size]]))
    sum_p = np.add.reduceat(p, starts)
    mean_f = np.add.reduceat(f, starts) / counts
    return mean_f, sum_p, counts.astype(float)


def whittle_fit(
    freqs_hz: np.ndarray,
    power: np.ndarray,
    use: np.ndarray,
    scale: float,
    start: NoiseModel,
    independent: float = 1.0,
) -> WhittleFit:
    """Maximum-Whittle-likelihood (net, fknee, alpha) for the periodogram ``power`` = |R_f|^2.

    ``independent``: v, the independent modes per mode (:func:`independent_fraction`), which
    scales the Fisher matrix.

    ``use`` selects the modes (DC and line bins excluded by the caller); ``scale`` = S_f/P(f)
    (:func:`periodogram_scale`); fmin and the pole tau are kept at ``start``'s. The white level is
    profiled analytically (S = c g(f; fk, alpha) gives c = sum |R_f|^2 / g / N_modes),
    (ln fk, alpha) by Nelder-Mead.
    """
    f_bin, p_bin, m_bin = _narrow_bins(freqs_hz, power, use)
    fmin = start.fmin_hz
    total = float(m_bin.sum())
    bounds = np.array([[math.log(1e-6), math.log(max(freqs_hz.max(), 1e-3))], [0.05, 6.0]])
    pole = rolloff(f_bin, start.tau_s**2)  # the detector's pole, held (:mod:`.rolloff`)

    def shape(theta):
        return scale * noise_psd(f_bin, 1.0, math.exp(theta[0]), theta[1], fmin) * pole

    def objective(theta):
        if np.any(theta < bounds[:, 0]) or np.any(theta > bounds[:, 1]):
            return np.inf
        g = shape(theta)
        c = float(np.sum(p_bin / g)) / total
        return 2 * total * (1 + math.log(c)) + 2 * float(np.sum(m_bin * np.log(g)))

    x0 = np.array([math.log(max(start.fknee_hz, 1e-5)), start.alpha])
    x0 = np.clip(x0, bounds[:, 0] + 1e-6, bounds[:, 1] - 1e-6)
    best = None
    for guess in (x0, np.array([x0[0] + 1.0, x0[1]]), np.array([x0[0] - 1.0, x0[1]])):
        guess = np.clip(guess, bounds[:, 0] + 1e-6, bounds[:, 1] - 1e-6)
        trial = scipy.optimize.minimize(
            objective,
            guess,
            method="Nelder-Mead",
            options={
                "xatol": 1e-5,
                "fatol": 1e-5,
                "maxiter": 1000,
                "initial_simplex": [guess, guess + [0.5, 0.0], guess + [0.0, 0.3]],
            },
        )
        if best is None or trial.fun < best.fun:
            best = trial
    log_fknee, alpha = best.x
    c = float(np.sum(p_bin / shape(best.x))) / total
    theta = np.array([0.5 * math.log(c), log_fknee, alpha])
    model = NoiseModel(math.exp(theta[0]), math.exp(log_fknee), float(alpha), fmin, start.tau_s)

    # Fisher matrix of ln L: sum over modes of d ln S / d theta_i d ln S / d theta_j.
    step = np.array([1e-5, 1e-4, 1e-4])
    grads = []
    for i in range(3):
        up, down = theta.copy(), theta.copy()
        up[i] += step[i]
        down[i] -= step[i]
        ln_up = np.log(noise_psd(f_bin, math.exp(up[0]), math.exp(up[1]), up[2], fmin))
        ln_down = np.log(noise_psd(f_bin, math.exp(down[0]), math.exp(down[1]), down[2], fmin))
        grads.append((ln_up - ln_down) / (2 * step[i]))
    grads = np.array(grads)
    fisher = independent * (grads * m_bin) @ grads.T
    try:
        covariance = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        covariance = np.linalg.pinv(fisher)
    return WhittleFit(model, covariance)
