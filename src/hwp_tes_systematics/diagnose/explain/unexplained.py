"""What the best fit cannot explain: significant structure left in the residual.

After the nominal adjustments and the selected effects, the residual r' = recording -
(adjusted nominal model + fitted effects) is searched again, against the fitted noise:

* lines (:func:`.locate.find_lines`: CLEAN with a look-elsewhere corrected 5 sigma
  threshold), named n f_HWP + m f_spin + k f_prec where a combination fits; lines found in
  several detectors at the same frequency are one entry. Where in time: the line's
  amplitude in 8 equal segments (the segments where it exceeds 3 sigma give the time
  range). A line at a pure sky frequency (n = 0: spin and precession combinations) is
  TOLERATED as the small unknown sky residual (a nominal adjustment) when its amplitude is
  below ``SKY_TOLERANCE`` (10 %) of the nominal sky + dipole signal at that frequency;
* bands of excess broadband power (mean |R_f|^2 / S_f over logarithmic bands, line bins
  excluded) above 5 sigma, from its Gamma tail with the look-elsewhere correction over
  the bands tested (:func:`.locate.excess_bands`);
* time segments (24 equal ones) whose whitened residual variance exceeds the noise by
  more than 5 sigma (chi^2 per segment against 2 m real dof, the variance the median
  segment's): a stretch where something happened that no effect models;
* transients that recur at one sky position (:func:`.effects.event_groups.sky_fixed_groups`:
  within a beam FWHM of each other, over more than one crossing, in any detector): a
  compact source the supplied sky map lacks, reported with its Galactic position, the
  crossings and the peak amplitude (the glitch fit leaves such events in the residual);
* the sky: structure fixed on the sky shows as lines at spin/precession combinations
  (n = 0) above the sky tolerance; their sky region is where the binned residual is
  largest (``sky_region``). (A correlation of the residual MAP with the intensity or the
  dipole is not used: with 1/f noise the pixels are not independent and any smooth map
  correlates with the dipole; the gain and sky-scale adjustments already fit those
  templates with the 1/f noise weights.)

Each entry says where it is, how significant, and which catalog effects were tried and
rejected (their Delta BIC at the last selection step, above the threshold). An effect
outside the catalog lands here instead of being forced onto the nearest catalog effect:
the selection takes an effect only for the part of the residual its forward model
explains, and whatever its templates cannot reach stays in r'.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import scipy.fft

from ...simulation import data_model
from ..effects import format_temperature
from ..effects.event_groups import event_directions, sky_fixed_groups
from ..effects.glitches import find_transients
from ..fourier import irfft, rfft
from ..locate import excess_bands, find_lines, line_at, sinusoid_fit, sky_residual
from ..model import Context
from ..noise import (
    NoiseModel,
    fitted_modes,
    independent_fraction,
    line_exclusion_mask,
    periodogram_scale,
)

SKY_TOLERANCE = 0.10
MIN_SIGMA = 5.0
LINE_SEGMENTS = 8
TIME_SEGMENTS = 24


def _line_time_range(residual, ctx: Context, k: int, freq_hz: float, noise: NoiseModel):
    """Segments (of LINE_SEGMENTS) where the line's amplitude exceeds 3 sigma: (t0, t1, amps)."""
    n = ctx.n_samples
    edges = np.linspace(0, n, LINE_SEGMENTS + 1).astype(int)
    psd = float(noise.psd(freq_hz))
    amplitudes, strong = [], []
    for i, (lo, hi) in enumerate(itertools.pairwise(edges)):
        valid = ctx.valid[k][lo:hi]
        if valid.sum() < 16:
            amplitudes.append(0.0)
            continue
        a, b = sinusoid_fit(residual[lo:hi], ctx.times_s[lo:hi], valid, freq_hz)
        amplitude = math.hypot(a, b)
        sigma = math.sqrt(psd / (valid.sum() / ctx.sampling_rate_hz))
        amplitudes.append(amplitude)
        if amplitude > 3 * sigma:
            strong.append(i)
    if not strong:
        return 0.0, ctx.duration_s, amplitudes
    t0 = edges[min(strong)] / ctx.sampling_rate_hz
    t1 = edges[max(strong) + 1] / ctx.sampling_rate_hz
    return float(t0), float(t1), amplitudes


def _rejected(history) -> dict:
    """Catalog effects tried at the last selection step and not selected: {name: (Delta BIC,
    screened)} (screened: the screen's Delta BIC, :mod:`..select.frozen`).

    A pass that offers only the held-out effects on unchanged weights ends on a step that
    tried those alone; the earlier final steps from the same fit (the same chi^2 before
    them) add what they tried."""
    final_steps = [s for s in history if s.added is None and s.removed is None and s.candidates]
    tried: dict[str, float] = {}
    for step in reversed(final_steps):
        if not math.isclose(step.chi2_before, final_steps[-1].chi2_before, rel_tol=1e-12):
            break
        for name, candidate in step.candidates.items():
            tried.setdefault(name, (float(candidate["delta_bic"]), bool(candidate.get("screened"))))
    return tried


def _unphysical(history) -> dict:
    """Effects the selection refused for their unphysical parameters: {name: why} (the
    latest refusal)."""
    found = {}
    for step in history:
        for name, candidate in (step.candidates or {}).items():
            if isinstance(candidate, dict) and candidate.get("unphysical"):
                found[name] = candidate["unphysical"]
    return found


def _tried_text(tried: dict, unphysical: dict) -> str:
    """The effects tried ({name: (Delta BIC, screened)}), in words: "name (Delta BIC +x[,
    screened][, rejected: ...])", ..."""
    said = []
    for name, (value, screened) in sorted(tried.items()):
        why = (
            f", rejected: outside physical bounds, {unphysical[name]}" if name in unphysical else ""
        )
        said.append(f"{name} (Delta BIC {value:+.0f}{', screened' if screened else ''}{why})")
    return ", ".join(said) or "none left to try"


def find_unexplained(
    ctx: Context,
    residual_after: np.ndarray,
    noise_models: list[NoiseModel],
    history: list,
    workers: int = 1,
) -> list[dict]:
    """Significant structure left after the best fit (module docstring), strongest first.
    ``history`` holds every step of every selection pass (:class:`..select.step.Selection`)."""
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    rejected = _rejected(history)
    tried_text = _tried_text(rejected, _unphysical(history))
    tried = {name: value for name, (value, _) in rejected.items()}
    nominal_signal = ctx.sky + ctx.dipole
    entries: dict[tuple, dict] = {}
    resolution = fs / n
    for k, det in enumerate(ctx.detector_names):
        for line in find_lines(residual_after[k], ctx, k, noise_models[k]):
            if line.n_hwp == 0:
                reference = line_at(nominal_signal[k], ctx.times_s, ctx.valid[k], line.freq_hz, 1.0)
                if line.amplitude_k < SKY_TOLERANCE * reference[0]:
                    continue  # within the tolerance for a small unknown sky residual
            key = (line.identification, round(line.freq_hz / (3 * resolution)))
            t0, t1, amplitudes = _line_time_range(
                residual_after[k], ctx, k, line.freq_hz, noise_models[k]
            )
            entry = entries.setdefault(
                key,
                {
                    "kind": "line",
                    "freq_hz": line.freq_hz,
                    "identification": line.identification,
                    "n_hwp": line.n_hwp,
                    "m_spin": line.m_spin,
                    "k_precession": line.k_precession,
                    "detectors": [],
                    "amplitude_k": {},
                    "significance_sigma": 0.0,
                    "global_significance_sigma": 0.0,
                    "time_range_s": [t0, t1],
                    "segment_amplitudes_k": {},
                    "tried_and_rejected": tried,
                },
            )
            if det not in entry["detectors"]:  # two findings in one detector's bins: one line
                entry["detectors"].append(det)
            # a line may be static (its amplitude) or only modulated (its rms change)
            modulated = line.modulation_sigma > line.significance_sigma
            entry["modulated"] = entry.get("modulated", False) or modulated
            entry["amplitude_k"][det] = line.amplitude_k
            entry.setdefault("modulation_k", {})[det] = line.modulation_k
            entry["segment_amplitudes_k"][det] = amplitudes
            entry["significance_sigma"] = max(
                entry["significance_sigma"], line.significance_sigma, line.modulation_sigma
            )
            entry["global_significance_sigma"] = max(
                entry["global_significance_sigma"], line.global_sigma
            )
            entry["time_range_s"] = [
                min(entry["time_range_s"][0], t0),
                max(entry["time_range_s"][1], t1),
            ]

    out = list(entries.values())
    if any(e["n_hwp"] == 0 for e in out):
        region = _sky_region(residual_after, ctx, noise_models)
        for entry in out:
            if entry["n_hwp"] == 0:
                entry["sky_region"] = region
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    modes = fitted_modes(n)
    lines = line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * resolution, 2e-4))
    residual_f = rfft(residual_after, axis=-1, workers=workers)
    transients = []
    for k, det in enumerate(ctx.detector_names):
        scale = periodogram_scale(n, fs, float(ctx.valid[k].mean()))
        s = scale * noise_models[k].psd(freqs)
        out += _bands(
            residual_f[k], freqs, s, modes & ~lines, det, tried, independent_fraction(ctx.valid[k])
        )
        out += _segments(residual_f[k], s, ctx, k, tried, workers)
        transients += find_transients(
            residual_f[k], s, ctx.valid[k], ctx.times_s, scale, k, workers=workers
        )
    out += _sky_fixed_transients(transients, ctx, tried)
    for entry in out:
        entry["text"] = describe(entry, tried_text)
    return sorted(out, key=lambda e: -e["significance_sigma"])


def _sky_region(residual_after, ctx: Context, noise_models) -> dict:
    """Galactic (lon, lat) [deg] of the 5 % of seen pixels where the binned residual is largest."""
    import healpy as hp

    sigma = np.array([m.net_k_sqrt_s * math.sqrt(ctx.sampling_rate_hz) for m in noise_models])
    sky = sky_residual(residual_after, ctx, sigma)
    if not sky.get("available") or "residual_map" not in sky:
        return {}
    values = sky["residual_map"]
    seen = np.flatnonzero(np.isfinite(values))
    if seen.size == 0:
        return {}
    top = seen[np.argsort(-np.abs(values[seen]))[: max(1, seen.size // 20)]]
    lon, lat = hp.pix2ang(sky["nside"], top, lonlat=True)
    return {
        "nside": int(sky["nside"]),
        "lon_deg": [float(np.min(lon)), float(np.max(lon))],
        "lat_deg": [float(np.min(lat)), float(np.max(lat))],
        "peak_lon_lat_deg": [float(lon[0]), float(lat[0])],
        "peak_residual_k": float(values[top[0]]),
    }


def _sky_fixed_transients(events, ctx: Context, tried) -> list[dict]:
    """Transients recurring at one sky position, one entry per position (strongest first)."""
    if ctx.pointings_ecl is None:
        return []
    rotation, _ = data_model.ecliptic_to_galactic()
    out = []
    for group in sky_fixed_groups(events, ctx.pointings_ecl, ctx.times_s, ctx.beam_arcmin):
        members = [events[i] for i in group]
        centre = event_directions(members, ctx.pointings_ecl, ctx.times_s).mean(axis=0)
        x, y, z = rotation @ (centre / np.linalg.norm(centre))
        strongest = max(members, key=lambda e: abs(e.amplitude_k))
        out.append(
            {
                "kind": "sky_fixed_transient",
                "galactic_lon_lat_deg": [
                    float(np.degrees(np.arctan2(y, x)) % 360),
                    float(np.degrees(np.arcsin(np.clip(z, -1, 1)))),
                ],
                "detectors": sorted({ctx.detector_names[e.detector] for e in members}),
                "times_s": [e.time_s for e in members],
                "peak_k": strongest.amplitude_k,
                "significance_sigma": max(e.significance for e in members),
                "tried_and_rejected": tried,
            }
        )
    return out


def _bands(residual_f, freqs, s, use, det, tried, valid_fraction) -> list[dict]:
    """:func:`..locate.frequency.excess_bands` above MIN_SIGMA, as entries of ``unexplained``."""
    return [
        {
            "kind": "band",
            "f_lo_hz": band["f_lo_hz"],
            "f_hi_hz": band["f_hi_hz"],
            "detectors": [det],
            "power_ratio": band["power_ratio"],
            "significance_sigma": band["significance_sigma"],
            "tried_and_rejected": tried,
        }
        for band in excess_bands(
            residual_f, freqs, s, use, det, min_sigma=MIN_SIGMA, valid_fraction=valid_fraction
        )
    ]


def _segments(residual_f, s, ctx: Context, k: int, tried, workers) -> list[dict]:
    """Time segments whose whitened residual variance exceeds the noise (> 5 sigma)."""
    n = ctx.n_samples
    high = np.arange(s.size) > 0.25 * s.size
    s_white = float(np.median(s[high]))
    whitening = np.sqrt(s_white / np.maximum(s, 1e-300))
    whitening[0] = 0.0
    z = irfft(residual_f * whitening, n=n, workers=workers)
    valid = ctx.valid[k]
    edges = np.linspace(0, n, TIME_SEGMENTS + 1).astype(int)
    # (lo, hi, valid samples, sum of z^2) of the segments with enough samples
    segments = [
        (lo, hi, int(valid[lo:hi].sum()), float(np.sum(z[lo:hi][valid[lo:hi]] ** 2)))
        for lo, hi in itertools.pairwise(edges)
        if valid[lo:hi].sum() >= 32
    ]
    # the whitened variance: the median segment's (robust to a few segments with events,
    # and unbiased where the residual is not Gaussian sample by sample, as a gain
    # fluctuation's sidebands, an amplitude-modulated carrier, are not)
    sigma2 = float(
        np.median([total / m for _, _, m, total in segments] or [np.mean(z[valid] ** 2)])
    )
    out = []
    for lo, hi, m, total in segments:
        chi2 = total / sigma2
        significance = (chi2 - m) / math.sqrt(2 * m)
        if significance > MIN_SIGMA:
            out.append(
                {
                    "kind": "time_segment",
                    "time_range_s": [lo / ctx.sampling_rate_hz, hi / ctx.sampling_rate_hz],
                    "detectors": [ctx.detector_names[k]],
                    "variance_ratio": chi2 / m,
                    "significance_sigma": significance,
                    "tried_and_rejected": tried,
                }
            )
    return out


def describe(entry: dict, tried_text: str) -> str:
    """One sentence: what is left, where, how significant, what was tried."""
    dets = " and ".join(entry["detectors"])
    if entry["kind"] == "line":
        amplitudes = ", ".join(format_temperature(v) for v in entry["amplitude_k"].values())
        if entry.get("modulated"):
            amplitudes += " static, changing in time by " + ", ".join(
                f"{format_temperature(v)} rms" for v in entry["modulation_k"].values()
            )
        where = entry["identification"]
        if where == "unidentified":
            where = "no combination n f_HWP + m f_spin + k f_prec"
        t0, t1 = entry["time_range_s"]
        region = entry.get("sky_region")
        if region:
            where += (
                f"; fixed on the sky, largest near Galactic (l, b) = "
                f"({region['peak_lon_lat_deg'][0]:.0f}, {region['peak_lon_lat_deg'][1]:.0f}) deg"
            )
        return (
            f"a line at {entry['freq_hz']:.6g} Hz ({where}) in {dets}, amplitude {amplitudes}, "
            f"{entry['significance_sigma']:.0f} sigma, present from t = {t0:.0f} s to {t1:.0f} s; "
            f"no catalog effect explains it (tried: {tried_text})"
        )
    if entry["kind"] == "band":
        return (
            f"excess broadband power x{entry['power_ratio']:.3g} over the fitted noise in "
            f"{entry['f_lo_hz']:.3g}-{entry['f_hi_hz']:.3g} Hz in {dets} "
            f"({entry['significance_sigma']:.0f} sigma), beyond a white + 1/f spectrum "
            f"(tried: {tried_text})"
        )
    if entry["kind"] == "time_segment":
        t0, t1 = entry["time_range_s"]
        return (
            f"the residual of {dets} is {entry['variance_ratio']:.3g} times the noise variance "
            f"from t = {t0:.0f} s to {t1:.0f} s ({entry['significance_sigma']:.0f} sigma): "
            f"something happened in that stretch that no effect models (tried: {tried_text})"
        )
    if entry["kind"] == "sky_fixed_transient":
        lon, lat = entry["galactic_lon_lat_deg"]
        times = ", ".join(f"{t:.0f}" for t in entry["times_s"])
        return (
            f"transients in {dets} that recur at one sky position, Galactic (l, b) = "
            f"({lon:.2f}, {lat:.2f}) deg, {len(entry['times_s'])} times (t = {times} s), "
            f"peak {format_temperature(entry['peak_k'])} ({entry['significance_sigma']:.0f} "
            "sigma): a compact source the supplied sky map lacks, not detector glitches "
            f"(which fall at random sky positions; tried: {tried_text})"
        )
    raise ValueError(f"unknown kind {entry['kind']!r}")
