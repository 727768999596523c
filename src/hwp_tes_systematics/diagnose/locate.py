"""Where the recording differs from the simulation: frequency, HWP angle, time and sky.

All on the residual r = recording - d_nom (flagged samples masked), against the noise
model P(f) of the residual (:mod:`.noise`).

Frequency (:func:`find_lines`). Blackman-Harris-windowed periodogram normalised by the
noise, z_f = |X_f|^2 / (P(f) f_s/2 sum w^2), exponentially distributed with mean 1 for
noise. The largest z above the threshold ln(N_f / p) (p = the one-sided 5 sigma tail
probability, N_f frequencies searched: a look-elsewhere corrected 5 sigma) is a line:
its frequency is refined by a parabola through log z, its amplitude and phase fitted by
least squares (a cos + b sin at that frequency, sigma_a = sqrt(P(f) / T_valid)), the
sinusoid is subtracted and the search repeated (CLEAN); a peak is searched only once
(a non-sinusoidal component, e.g. a drifting line, leaves power CLEAN cannot remove) and
fits below 5 sigma are not reported. The line is fitted with a slowly varying amplitude,
sum_{j<=3} P_j(x) (a_j cos + b_j sin), so that a drifting line (gain or HWP temperature
drift) is one line with a "modulation", not a comb of lines. Each line is named by the
simplest combination n f_HWP + m f_spin + k f_prec (0 <= n <= 8, |m|, |k| <= 3; spin
and precession terms only when resolved, >= 2 frequency bins) within 3 bins
(complexity (n > 0) + |m| + |k| first, then distance), and then fitted AT that
combination's frequency ("offset_hz" is how far the periodogram peak was). The
dipole sits at f_spin and its precession sidebands, so "2 f_HWP +- f_spin" are the
HWPSS x dipole intermodulation lines. Excess bands: the mean of |R_f|^2 / S_nom,f over
logarithmic bands (line bins excluded); for noise it is the mean of m unit exponentials,
Gamma(m, 1/m), whose tail (not the Gaussian 1 +- 1/sqrt(m), which at m ~ 20 calls a
4 sigma excess 5 sigma) gives the band's probability, corrected for the bands tested.

HWP angle (:func:`hwp_profile`). Residual averaged in 64 bins of chi (per detector),
and the amplitudes of n = 1..8 harmonics A_n cos(n chi - phi_n) by least squares on
all valid samples, sigma = sigma_white sqrt(2 / N_valid).

Time. Transients (:func:`find_transients`): the residual whitened by sqrt(S_white / S_f)
is thresholded at ``threshold_sigma`` robust standard deviations (1.4826 x the median
absolute deviation) and each group of hits fitted as A exp(-(t - t0)/tau). Drifts
(:func:`drifts`): whitened least-squares (Fourier domain, weights 1/S_f, so the 1/f noise
is accounted for) of the residual on P1(x) (offset slope), on [1, P1] x cos 2(chi - theta)
and sin (2f amplitude drift) and on [1, P1] x D (dipole gain drift), with uncertainties.

Sky (:func:`sky_residual`). Residual binned in Galactic pixels (nside 32, or the sky
map's if coarser); Pearson correlation (Fisher z = atanh(r) sqrt(N_pix - 3)) and the
least-squares coefficients of the residual map on the binned nominal intensity and
dipole maps.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.fft
import scipy.signal
import scipy.special
import scipy.stats

from .effects.glitches import GlitchEvent, find_transients
from .linalg import whitened_lstsq
from .model import Context
from .noise import (
    NoiseModel,
    fitted_modes,
    independent_fraction,
    line_exclusion_mask,
    periodogram_scale,
)

FIVE_SIGMA_P = float(scipy.stats.norm.sf(5.0))
MAX_LINES = 25
HWP_BINS = 64
MAX_HARMONIC = 8
SKY_NSIDE = 32


def p_to_sigma(p: float) -> float:
    """One-sided Gaussian significance of a tail probability."""
    p = min(max(p, 1e-300), 0.5)
    return float(scipy.stats.norm.isf(p))


# --------------------------------------------------------------------------- lines


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
        spectrum = scipy.fft.rfft(work * window)
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


# --------------------------------------------------------------------------- HWP angle


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


# --------------------------------------------------------------------------- time


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
    templates_f = scipy.fft.rfft(np.stack(rows) * ctx.valid[k], axis=-1, workers=workers)
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


# --------------------------------------------------------------------------- sky


def coarse_pixels(ctx: Context, nside_out: int = SKY_NSIDE):
    """Galactic pixels at min(nside_out, the sky map's nside), RING, (n_det, n)."""
    import healpy as hp

    nside = ctx.nside
    if nside is None or ctx.pixels is None:
        return None, None
    if nside <= nside_out:
        return ctx.pixels, nside
    factor = round(math.log2(nside / nside_out))
    if 2**factor * nside_out != nside:
        return ctx.pixels, nside
    nest = hp.ring2nest(nside, ctx.pixels)
    return hp.nest2ring(nside_out, nest >> (2 * factor)), nside_out


def bin_map(pixels, values, valid, npix):
    hits = np.bincount(pixels[valid], minlength=npix)
    sums = np.bincount(pixels[valid], weights=values[valid], minlength=npix)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(hits > 0, sums / np.maximum(hits, 1), np.nan), hits


def sky_residual(residual: np.ndarray, ctx: Context, sigma_sample: np.ndarray) -> dict:
    """Residual map and its correlation with the intensity and dipole maps (all detectors)."""
    pixels, nside = coarse_pixels(ctx)
    if pixels is None:
        return {"available": False}
    npix = 12 * nside * nside
    valid = ctx.valid.ravel()
    pix = pixels.ravel()
    weights = np.repeat(1.0 / np.asarray(sigma_sample) ** 2, ctx.n_samples)
    hits = np.bincount(pix[valid], minlength=npix)
    wsum = np.bincount(pix[valid], weights=weights[valid], minlength=npix)

    def weighted(values):
        sums = np.bincount(pix[valid], weights=(values.ravel() * weights)[valid], minlength=npix)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(hits > 0, sums / np.maximum(wsum, 1e-300), np.nan)

    # the offset is a nuisance (DC is not fitted): remove each detector's mean first
    centred = (
        residual
        - np.array([residual[k][ctx.valid[k]].mean() for k in range(ctx.n_detectors)])[:, None]
    )
    residual_map = weighted(centred)
    intensity_map = weighted(ctx.sky_intensity)
    dipole_map = weighted(ctx.dipole)
    seen = hits > 0
    noise_map = np.where(seen, 1.0 / np.sqrt(np.maximum(wsum, 1e-300)), np.nan)
    out = {"available": True, "nside": nside, "n_pixels": int(seen.sum())}
    if seen.sum() < 5:
        return out | {"residual_map": residual_map, "hits": hits}
    for name, template in (("intensity", intensity_map), ("dipole", dipole_map)):
        x, y, e = template[seen], residual_map[seen], noise_map[seen]
        if np.std(x) == 0 or np.std(y) == 0:
            r = 0.0
        else:
            r = float(np.corrcoef(x, y)[0, 1])
        z = float(np.arctanh(np.clip(r, -0.999999, 0.999999)) * math.sqrt(max(seen.sum() - 3, 1)))
        design = np.column_stack([x - x.mean(), np.ones_like(x)]) / e[:, None]
        coefficients, *_ = np.linalg.lstsq(design, y / e, rcond=None)
        cov = np.linalg.pinv(design.T @ design)
        out[name] = {
            "correlation": r,
            "fisher_z_sigma": z,
            "coefficient": float(coefficients[0]),
            "sigma_coefficient": float(math.sqrt(max(cov[0, 0], 0.0))),
        }
    out["residual_map"] = residual_map
    out["hits"] = hits
    return out


# --------------------------------------------------------------------------- report


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
        residual_f = scipy.fft.rfft(residual, axis=-1, workers=workers)
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
