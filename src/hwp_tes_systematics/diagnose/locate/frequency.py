"""Where in frequency: lines (CLEAN on the noise-normalised periodogram) and excess bands
(:mod:`hwp_tes_systematics.diagnose.locate`, "Frequency")."""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass

import numpy as np
import scipy.fft
import scipy.signal
import scipy.special
import scipy.stats

from ..fourier import rfft
from ..model import Context
from ..noise import (
    NoiseModel,
)

FIVE_SIGMA_P = float(scipy.stats.norm.sf(5.0))
MAX_LINES = 25
MAX_HARMONIC = 8


def p_to_sigma(p: float) -> float:
    """One-sided Gaussian significance of a tail probability."""
    p = min(max(p, 1e-300), 0.5)
    return float(scipy.stats.norm.isf(p))


@dataclass
class Line:
    detector: str
    freq_hz: float
    amplitude_k: float
    sigma_amplitude_k: float
    phase_rad: float
    significance_sigma: float  # A / sigma_A of the least-squares fit
    global_sigma: float  # look-elsewhere corrected significance of the periodogram peak
    modulation_k: float  # rms of the slow amplitude modulation sum_{j=1..3} P_j(x) (a_j, b_j)
    modulation_sigma: float  # its significance (chi^2 of a_j, b_j, j >= 1, as sigma)
    identification: str
    n_hwp: int | None
    m_spin: int | None
    k_precession: int | None
    offset_hz: float | None

    def as_dict(self) -> dict:
        return asdict(self)


def identify(
    freq_hz: float,
    f_hwp_hz: float,
    f_spin_hz: float,
    f_prec_hz: float,
    tol_hz: float,
    resolution_hz: float = 0.0,
):
    """Simplest n f_HWP + m f_spin + k f_prec within ``tol_hz``: (label, n, m, k, offset).

    A spin or precession term enters only if that frequency is resolved (>= 2
    ``resolution_hz``): a 2-hour recording cannot tell 2 f_HWP from 2 f_HWP + f_prec.
    """
    best = None
    spins = range(-3, 4) if f_spin_hz >= 2 * resolution_hz else (0,)
    precessions = range(-3, 4) if f_prec_hz >= 2 * resolution_hz else (0,)
    for n in range(MAX_HARMONIC + 1):
        for m in spins:
            for k in precessions:
                if n == 0 and (m < 0 or (m == 0 and k <= 0)):
                    continue
                center = n * f_hwp_hz + m * f_spin_hz + k * f_prec_hz
                offset = freq_hz - center
                if center <= 0 or abs(offset) > tol_hz:
                    continue
                key = ((n > 0) + abs(m) + abs(k), abs(offset))
                if best is None or key < best[0]:
                    best = (key, n, m, k, offset)
    if best is None:
        return "unidentified", None, None, None, None
    _, n, m, k, offset = best
    parts = []
    for count, name in ((n, "f_HWP"), (m, "f_spin"), (k, "f_prec")):
        if count == 0:
            continue
        sign = "-" if count < 0 else "+"
        size = abs(count)
        term = f"{size} {name}" if size != 1 else name
        parts.append((sign, term))
    label = parts[0][1] if parts[0][0] == "+" else "-" + parts[0][1]
    for sign, term in parts[1:]:
        label += f" {sign} {term}"
    if n == 0 and m == 1:
        label += " (dipole)"
    return label, n, m, k, offset


def sinusoid_fit(residual, times_s, valid, freq_hz):
    """Least-squares a cos(2 pi f t) + b sin(2 pi f t) + c on the valid samples: (a, b)."""
    phase = 2 * np.pi * freq_hz * times_s
    design = np.empty((times_s.size, 3))
    design[:, 0] = np.cos(phase)
    design[:, 1] = np.sin(phase)
    design[:, 2] = 1.0
    design *= valid[:, None]
    coefficients = np.linalg.lstsq(design.T @ design, design.T @ (residual * valid), rcond=None)[0]
    return float(coefficients[0]), float(coefficients[1])


def modulated_line_fit(residual, ctx: Context, valid, freq_hz, degree: int = 3):
    """Least squares sum_{j<=degree} P_j(x) [a_j cos(2 pi f t) + b_j sin(2 pi f t)] + c.

    Returns (a, b, model): a line with a slowly varying amplitude (a drifting HWPSS or
    gain) is one component, not a comb of spurious lines around it.
    """
    phase = 2 * np.pi * freq_hz * ctx.times_s
    cos, sin = np.cos(phase), np.sin(phase)
    design = np.empty((ctx.n_samples, 2 * degree + 3))
    for j in range(degree + 1):
        legendre = ctx.legendre(j)
        design[:, j] = legendre * cos
        design[:, degree + 1 + j] = legendre * sin
    design[:, -1] = 1.0
    weight = valid.astype(float)
    weighted = design * weight[:, None]
    coefficients = np.linalg.lstsq(weighted.T @ design, weighted.T @ residual, rcond=None)[0]
    a = coefficients[: degree + 1]
    b = coefficients[degree + 1 : 2 * degree + 2]
    model = design[:, :-1] @ coefficients[:-1]
    return a, b, model * weight


def line_at(residual, times_s, valid, freq_hz, psd_at_f):
    """(amplitude, sigma, phase, significance, a, b) of a line at a known frequency.

    a cos(2 pi f t) + b sin(2 pi f t) = A cos(2 pi f t + phase); sigma_A = sqrt(P(f) / T_valid).
    """
    a, b = sinusoid_fit(residual, times_s, valid, freq_hz)
    duration = valid.sum() * (times_s[1] - times_s[0])
    sigma = math.sqrt(max(psd_at_f, 0.0) / max(duration, 1e-9))
    amplitude = math.hypot(a, b)
    significance = amplitude / sigma if sigma > 0 else 0.0
    return amplitude, sigma, math.atan2(-b, a), significance, a, b


def find_lines(
    residual: np.ndarray,
    ctx: Context,
    k: int,
    noise: NoiseModel,
    max_lines: int = MAX_LINES,
    false_alarm_p: float = FIVE_SIGMA_P,
    min_significance: float = 5.0,
) -> list[Line]:
    """Significant lines of detector k's residual, strongest first (CLEAN, module docstring)."""
    fs = ctx.sampling_rate_hz
    n = residual.size
    valid = ctx.valid[k]
    work = np.where(valid, residual, 0.0)
    window = scipy.signal.windows.blackmanharris(n) * valid
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    psd = noise.psd(freqs)
    norm = psd * fs / 2 * np.sum(window**2)
    resolution = fs / n
    searched = freqs > 4 * resolution
    searched[-1] = False
    n_trials = int(searched.sum())
    threshold = math.log(n_trials / false_alarm_p)
    tolerance = 3 * resolution
    lines: list[Line] = []
    for _ in range(2 * max_lines):
        if len(lines) >= max_lines:
            break
        spectrum = rfft(work * window)
        z = (spectrum.real**2 + spectrum.imag**2) / norm
        z[~searched] = 0.0
        peak = int(np.argmax(z))
        if z[peak] < threshold:
            break
        # a component that CLEAN cannot remove (not a sinusoid) is searched only once
        searched[max(0, peak - 1) : peak + 2] = False
        freq = freqs[peak]
        if 0 < peak < z.size - 1 and z[peak - 1] > 0 and z[peak + 1] > 0:
            lo, mid, hi = np.log(z[peak - 1 : peak + 2])
            denominator = lo - 2 * mid + hi
            if denominator < 0:
                freq += 0.5 * (lo - hi) / denominator * resolution
        label, n_h, m_s, k_p, offset = identify(
            freq, ctx.f_hwp_hz, ctx.f_spin_hz, ctx.f_precession_hz, tolerance, resolution
        )
        if offset is not None:  # fit at the exact combination (a modulated line peaks off it)
            freq -= offset
        a, b, model = modulated_line_fit(work, ctx, valid, freq)
        work = work - model
        duration = valid.sum() / fs
        sigma = math.sqrt(float(noise.psd(freq)) / duration)
        amplitude = math.hypot(a[0], b[0])
        significance = amplitude / sigma if sigma > 0 else 0.0
        # sum_t P_j^2 = N / (2 j + 1): sigma(a_j) = sigma sqrt(2 j + 1)
        orders = np.arange(1, a.size)
        modulation_chi2 = float(np.sum((a[1:] ** 2 + b[1:] ** 2) / (sigma**2 * (2 * orders + 1))))
        modulation = math.sqrt(float(np.sum((a[1:] ** 2 + b[1:] ** 2) / (2 * (2 * orders + 1)))))
        if max(significance, math.sqrt(modulation_chi2)) < min_significance:
            continue
        lines.append(
            Line(
                detector=ctx.detector_names[k],
                freq_hz=float(freq),
                amplitude_k=amplitude,
                sigma_amplitude_k=sigma,
                phase_rad=math.atan2(-b[0], a[0]),
                significance_sigma=significance,
                global_sigma=p_to_sigma(min(1.0, n_trials * math.exp(-float(z[peak])))),
                modulation_k=modulation,
                modulation_sigma=p_to_sigma(
                    float(scipy.stats.chi2.sf(modulation_chi2, 2 * orders.size))
                ),
                identification=label,
                n_hwp=n_h,
                m_spin=m_s,
                k_precession=k_p,
                offset_hz=offset,
            )
        )
    return lines


def excess_bands(
    residual_f: np.ndarray,
    freqs: np.ndarray,
    s_nom: np.ndarray,
    use: np.ndarray,
    detector: str,
    per_decade: int = 3,
    min_sigma: float = 5.0,
    valid_fraction: float = 1.0,
) -> list[dict]:
    """Bands where the residual power exceeds the noise S_nom: the mean ratio
    x = mean |R_f|^2 / S_nom,f over a band's m modes is Gamma(m, 1/m) for noise, so the
    band's tail probability is p = Q(m, m x) (regularised upper incomplete gamma);
    ``significance_sigma`` is the look-elsewhere corrected one, p x the bands tested
    (``local_significance_sigma`` without), and a band is kept above ``min_sigma``.

    With a fraction v of the samples valid the modes are correlated through the mask's
    spectrum W: sum_f' |W(f - f')|^2 / W(0)^2 = 1 / v (Parseval), so a band of m modes
    holds m v independent ones and m is replaced by m v (``valid_fraction`` = v)."""
    ratio = (residual_f.real**2 + residual_f.imag**2) / np.maximum(s_nom, 1e-300)
    positive = freqs[use]
    if positive.size == 0:
        return []
    edges = np.logspace(
        np.log10(positive.min()),
        np.log10(positive.max()) + 1e-9,
        max(2, int(per_decade * np.log10(positive.max() / positive.min())) + 2),
    )
    tested = []  # (lo, hi, modes, mean ratio, tail probability)
    for lo, hi in itertools.pairwise(edges):
        band = use & (freqs >= lo) & (freqs < hi)
        m = int(band.sum())
        if m < 10:
            continue
        mean = float(ratio[band].mean())
        independent = m * min(max(valid_fraction, 1e-3), 1.0)
        tested.append(
            (lo, hi, m, mean, float(scipy.special.gammaincc(independent, independent * mean)))
        )
    out = []
    for lo, hi, m, mean, p in tested:
        significance = p_to_sigma(min(1.0, len(tested) * p))
        if significance > min_sigma:
            out.append(
                {
                    "detector": detector,
                    "f_lo_hz": float(lo),
                    "f_hi_hz": float(hi),
                    "power_ratio": mean,
                    "significance_sigma": significance,
                    "local_significance_sigma": p_to_sigma(p),
                    "n_modes": m,
                }
            )
    return out
