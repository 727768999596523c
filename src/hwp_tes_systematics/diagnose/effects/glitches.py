"""Cosmic-ray glitches: the event model, its per-event fit, the detection in a whitened
residual and the catalog effect (how the events group, on the sky or in time:
:mod:`.event_groups`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.fft
import scipy.optimize

from ..fourier import irfft
from .base import Effect, format_temperature, register
from .event_groups import coincidence_scope, coincidence_sentence, coincidences, sky_fixed_groups


@dataclass(frozen=True)
class GlitchEvent:
    """A cosmic-ray hit: A exp(-(t - t0)/tau) for t >= t0 (t0 = the first affected sample),
    plus ``departure_k``: where the data ask for it, the event's first samples' departures
    from that tail (a readout's anti-aliasing or decimation filter shapes and can ring a
    hit faster than a sample), one free value per sample."""

    detector: int
    time_s: float
    amplitude_k: float
    tau_s: float
    sigma_amplitude_k: float = 0.0
    sigma_tau_s: float = 0.0
    significance: float = 0.0
    departure_k: tuple[float, ...] = ()
    sigma_departure_k: float = 0.0  # each departure's error: the white noise per sample

    @property
    def n_parameters(self) -> int:
        """Amplitude, time, tail and one per sample of departure (the BIC's count)."""
        return 3 + len(self.departure_k)


GLITCH_TAIL_CUT = 25.0  # the exponential tail is evaluated over 25 tau
# a hit's first samples may depart from an exponential tail over this long (a readout
# filter's response); at least DEPARTURE_MIN_SAMPLES samples
DEPARTURE_S = 0.25
DEPARTURE_MIN_SAMPLES = 3
MAX_EVENTS_PER_GROUP = 10  # hits fitted in one group of samples above the threshold


def departure_samples(dt_s: float) -> int:
    """P, the samples a hit may depart over: ceil(DEPARTURE_S / dt), at least
    DEPARTURE_MIN_SAMPLES (the 1e-3 absorbs an interval read from rounded times)."""
    return max(DEPARTURE_MIN_SAMPLES, math.ceil(DEPARTURE_S / dt_s - 1e-3))


def glitch_profile(
    times_s: np.ndarray, time_s: float, amplitude_k: float, tau_s: float, departure_k=()
):
    """(first index, values) of one event: A exp(-(t - t0)/tau) at samples t >= t0, plus
    ``departure_k`` on its first samples."""
    first = int(np.searchsorted(times_s, time_s - 1e-9))
    dt = times_s[1] - times_s[0] if times_s.size > 1 else 1.0
    length = max(1, int(np.ceil(GLITCH_TAIL_CUT * max(tau_s, 1e-6) / dt)) + 1, len(departure_k))
    stop = min(times_s.size, first + length)
    values = amplitude_k * np.exp(-(times_s[first:stop] - time_s) / max(tau_s, 1e-9))
    shaped = min(len(departure_k), values.size)
    values[:shaped] += np.asarray(departure_k[:shaped], dtype=float)
    return first, values


def glitch_tod(times_s: np.ndarray, n_detectors: int, events) -> np.ndarray:
    """Sum of the events' exponential tails and departures, (n_det, n)."""
    out = np.zeros((n_detectors, times_s.size))
    for event in events:
        first, values = glitch_profile(
            times_s, event.time_s, event.amplitude_k, event.tau_s, event.departure_k
        )
        out[event.detector, first : first + values.size] += values
    return out


def fit_glitch(
    residual: np.ndarray,
    times_s: np.ndarray,
    index: int,
    sigma_k: float,
    detector: int,
    tau_guess_s: float,
    window_s: float = 4.0,
    departure_chi2_per_sample: float | None = None,
) -> GlitchEvent | None:
    """Nonlinear least-squares fit of one event at sample ``index`` (the first hit sample).

    Model on a window around the event: c + A exp(-(t - t0)/tau) (t >= t0), with c a local
    offset (1/f noise, slow signals); ``scipy.optimize.least_squares`` over (c, A, ln tau);
    uncertainties from the Jacobian with the white noise ``sigma_k`` per sample. With
    ``departure_chi2_per_sample`` (the BIC's ln N per parameter), the residual of the
    event's first P samples (DEPARTURE_S, at least DEPARTURE_MIN_SAMPLES) is kept as its
    departure from the tail when its chi^2 exceeds P times that: one free value per sample,
    each with the error sigma_k.
    """
    dt = times_s[1] - times_s[0]
    half = max(8, int(window_s / dt))
    lo, hi = max(0, index - half // 4), min(times_s.size, index + half)
    t = times_s[lo:hi]
    y = residual[lo:hi]
    t0 = times_s[index]
    after = t >= t0 - 1e-9

    def model(theta):
        c, amplitude, log_tau = theta
        out = np.full_like(t, c)
        out[after] += amplitude * np.exp(-(t[after] - t0) / np.exp(log_tau))
        return out

    def fun(theta):
        return (model(theta) - y) / sigma_k

    start = np.array(
        [np.median(y[~after]) if np.any(~after) else 0.0, y[after][0], np.log(tau_guess_s)]
    )
    start[1] -= start[0]
    try:
        solution = scipy.optimize.least_squares(
            fun,
            start,
            bounds=([-np.inf, -np.inf, np.log(0.05 * dt)], [np.inf, np.inf, np.log(5.0)]),
        )
    except ValueError:
        return None
    jac = solution.jac
    try:
        cov = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return None
    _c, amplitude, log_tau = solution.x
    tau = float(np.exp(log_tau))
    sigma_amplitude = float(np.sqrt(max(cov[1, 1], 0.0)))
    sigma_tau = float(tau * np.sqrt(max(cov[2, 2], 0.0)))
    departure: tuple[float, ...] = ()
    if departure_chi2_per_sample is not None:
        n_shaped = departure_samples(dt)
        first = int(np.flatnonzero(after)[0])
        left = (y - model(solution.x))[first : first + n_shaped]
        if float(np.sum((left / sigma_k) ** 2)) > left.size * departure_chi2_per_sample:
            departure = tuple(float(v) for v in left)
    return GlitchEvent(
        detector=detector,
        time_s=float(t0),
        amplitude_k=float(amplitude),
        tau_s=tau,
        sigma_amplitude_k=sigma_amplitude,
        sigma_tau_s=sigma_tau,
        significance=float(abs(amplitude) / sigma_amplitude) if sigma_amplitude > 0 else 0.0,
        departure_k=departure,
        sigma_departure_k=float(sigma_k) if departure else 0.0,
    )


@register
class Glitches(Effect):
    """Cosmic-ray glitches: sum_i A_i exp(-(t - t_i)/tau_i) for t >= t_i.

    t_i is the first affected sample (a hit between two samples is the same model with A
    scaled by exp(-delta/tau)). Detection: samples of the whitened residual above a robust
    threshold (median absolute deviation), then a nonlinear fit per event (:func:`fit_glitch`).
    A hit whose first samples (0.25 s, at least three) depart from the tail by more than
    the BIC pays (ln N per sample: a readout filter's response to a hit faster than a
    sample, which can ring) keeps those departures, one value per sample; the report
    gives the largest as ``departure``.
    """

    name = "glitches"
    title = "cosmic-ray glitches"
    parameters: ClassVar[dict[str, str]] = {
        "amplitude": "K",
        "time": "s",
        "tau": "s",
        "departure": "K",
    }
    events: ClassVar[bool] = True
    main_parameters = ("amplitude",)
    kind = "events"
    stage = "events"
    signature = "isolated transients in time, uncorrelated with chi and the sky"
    discrimination = (
        "found by robust (MAD) thresholding of the whitened residual and fitted per event; "
        "not periodic in chi, no lines; at random sky positions (transients recurring at one "
        "sky position are a source missing from the sky map: unexplained, with the position)"
    )

    # per event: amplitude, time and tail (the BIC's count; a departure adds one per sample)
    parameters_per_event = 3

    @classmethod
    def detect(cls, r_f, s, valid, times_s, scale, detector, threshold_sigma, ln_n, workers=1):
        """The events in one detector's residual (rfft ``r_f``, noise periodogram ``s``):
        :func:`find_transients`, each kept when its significance pays its BIC penalty
        (``parameters_per_event`` ln N) and its departure from an exponential tail when
        that pays ln N per sample."""
        return find_transients(
            r_f,
            s,
            valid,
            times_s,
            scale,
            detector,
            threshold_sigma=threshold_sigma,
            min_significance=math.sqrt(cls.parameters_per_event * ln_n),
            workers=workers,
            departure_chi2_per_sample=ln_n,
        )

    def find(self, problem, k: int, r_f: np.ndarray, bank=None, gram=None) -> list:
        """The events in detector k's residual ``r_f``: :meth:`detect` with the problem's
        noise, threshold and ln N_eff (a hit is short: the linear templates ``bank`` are
        not needed)."""
        return self.detect(
            r_f,
            problem.s_nom[k],
            problem.valid[k],
            problem.ctx.times_s,
            problem.scale[k],
            k,
            threshold_sigma=problem.glitch_threshold_sigma,
            ln_n=problem.ln_n_eff,
            workers=problem.workers,
        )

    @staticmethod
    def detector_events(ctx, events) -> list:
        """The events that are detector events: those recurring at one sky position
        (:func:`sky_fixed_groups`) are a sky signal the model lacks, left in the residual
        for :mod:`.unexplained` to report with their position."""
        if ctx.pointings_ecl is None:
            return events
        groups = sky_fixed_groups(events, ctx.pointings_ecl, ctx.times_s, ctx.beam_arcmin)
        on_sky = {i for group in groups for i in group}
        return [e for i, e in enumerate(events) if i not in on_sky]

    @staticmethod
    def events_tod(ctx, events) -> np.ndarray:
        """The events' TOD, (n_det, n): :func:`glitch_tod`."""
        return glitch_tod(ctx.times_s, ctx.n_detectors, events)

    def reported_parameters(self, fit, detector_names, sampling_rate_hz, units) -> dict:
        """Per event i: "glitch<i>.amplitude|time|tau[<detector>]" -> {value, sigma, unit,
        detector, parameter}, the events in detector and time order."""
        out = {}
        for i, e in enumerate(sorted(fit.events, key=lambda e: (e.detector, e.time_s))):
            det = detector_names[e.detector]
            out[f"glitch{i}.amplitude[{det}]"] = {
                "value": e.amplitude_k,
                "sigma": e.sigma_amplitude_k,
                "unit": "K",
                "detector": det,
                "parameter": "amplitude",
            }
            out[f"glitch{i}.time[{det}]"] = {
                "value": e.time_s,
                "sigma": 0.5 / sampling_rate_hz,  # on the sampling grid
                "unit": "s",
                "detector": det,
                "parameter": "time",
            }
            out[f"glitch{i}.tau[{det}]"] = {
                "value": e.tau_s,
                "sigma": e.sigma_tau_s,
                "unit": "s",
                "detector": det,
                "parameter": "tau",
            }
            if e.departure_k:  # the largest of its first samples' departures from the tail
                largest = max(e.departure_k, key=abs)
                out[f"glitch{i}.departure[{det}]"] = {
                    "value": largest,
                    "sigma": e.sigma_departure_k,
                    "unit": "K",
                    "detector": det,
                    "parameter": "departure",
                }
        return out

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        events = params.get("events", [])
        events = [e if isinstance(e, GlitchEvent) else GlitchEvent(*e) for e in events]
        return tod + glitch_tod(ctx.times_s, tod.shape[0], events)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        events = fit.events
        if not events:
            return "no transient left after the fit"
        strongest = max(events, key=lambda e: e.significance)
        taus = np.array([e.tau_s for e in events])
        names = ev.ctx.detector_names
        per_det = {name: sum(e.detector == k for e in events) for k, name in enumerate(names)}
        counts = ", ".join(f"{n} in {name}" for name, n in per_det.items())
        shaped = [e for e in events if e.departure_k]
        departures = (
            f"; {len(shaped)} depart from an exponential tail on their first "
            f"{len(shaped[0].departure_k)} samples (up to "
            f"{max(abs(v) / abs(e.amplitude_k) for e in shaped for v in e.departure_k):.0%} "
            "of the amplitude: a readout filter's response to a hit faster than a sample)"
            if shaped
            else ""
        )
        return (
            f"{len(events)} isolated transients ({counts}); the strongest "
            f"{format_temperature(strongest.amplitude_k)} at t = {strongest.time_s:.2f} s ({strongest.significance:.0f} "
            f"sigma) in {names[strongest.detector]}; exponential tails tau = "
            f"{np.median(taus) * 1e3:.0f} ms (median){departures}; localised in time, not "
            "periodic in chi"
            + (
                "; " + coincidence_sentence(coincidences(events, ev.ctx.times_s, ev.ctx.valid))
                if len(names) > 1
                else ""
            )
        )

    def scope(self, ctx, fit=None) -> dict:
        """Per detector, or, where its events coincide across detectors more than chance
        (:func:`coincidences`), by coincidence: {"by": "coincidence", "groups": {"t = ..
        s": the detectors sharing that event}, "observed_pairs", "expected_pairs",
        "p_value"}."""
        if fit is None or ctx.n_detectors < 2 or not fit.events:
            return super().scope(ctx)
        found = coincidences(fit.events, ctx.times_s, ctx.valid)
        if not found.significant:
            return super().scope(ctx)
        return coincidence_scope(found, fit.events, ctx.detector_names)


def find_transients(
    r_f: np.ndarray,
    s: np.ndarray,
    valid: np.ndarray,
    times_s: np.ndarray,
    scale: float,
    detector: int,
    threshold_sigma: float = 5.0,
    min_significance: float = 0.0,
    workers: int = 1,
    departure_chi2_per_sample: float | None = None,
) -> list[GlitchEvent]:
    """Transients in a residual given by its rfft r_f, with S_f the expected |R_f|^2 of noise.

    Whitened residual z = irfft(r_f sqrt(S_white / S_f)); hits where |z| exceeds
    ``threshold_sigma`` x 1.4826 MAD(z); hits closer than 10 samples form one group, fitted
    at its largest residual sample by :func:`.effects.fit_glitch`, then, with that event
    subtracted, at the largest sample still above the threshold that starts a later hit
    (at least the departures' length, DEPARTURE_S, after the events fitted: two hits
    closer than that are one event with departures; a jump above the threshold from the
    sample before), until none is left; events whose A / sigma_A is below
    ``min_significance`` are dropped (and end their group's search);
    ``departure_chi2_per_sample``: :func:`fit_glitch`'s.
    """
    n = valid.size
    fs = 1.0 / (times_s[1] - times_s[0])
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    r_time = irfft(r_f, n=n, workers=workers) * valid
    high = freqs > 0.25 * freqs[-1]
    s_white = float(np.median(s[high])) if high.any() else float(np.median(s[1:]))
    whitening = np.sqrt(s_white / np.maximum(s, 1e-300))
    whitening[0] = 0.0
    z = irfft(r_f * whitening, n=n, workers=workers)
    zv = z[valid]
    sigma = 1.4826 * float(np.median(np.abs(zv - np.median(zv))))
    if not sigma > 0:
        return []
    hits = np.flatnonzero((np.abs(z) > threshold_sigma * sigma) & valid)
    if hits.size == 0:
        return []
    groups = np.split(hits, np.flatnonzero(np.diff(hits) > 10) + 1)
    sigma_sample = math.sqrt(s_white / scale * fs / 2)
    n_apart = departure_samples(1.0 / fs)
    events = []
    for group in groups[:1000]:
        candidates, peaks = group, []
        while candidates.size and len(peaks) < MAX_EVENTS_PER_GROUP:
            peak = int(candidates[np.argmax(np.abs(r_time[candidates]))])
            event = fit_glitch(
                r_time,
                times_s,
                peak,
                sigma_sample,
                detector,
                1.5 / fs,
                departure_chi2_per_sample=departure_chi2_per_sample,
            )
            if event is None or event.significance <= min_significance:
                break
            events.append(event)
            peaks.append(peak)
            first, values = glitch_profile(
                times_s, event.time_s, event.amplitude_k, event.tau_s, event.departure_k
            )
            r_time[first : first + values.size] -= values * valid[first : first + values.size]
            z[first : first + values.size] -= values  # the whitening is ~1 at a hit's scale
            # a later hit: after the events fitted by the departures' length, with an onset
            # (a jump from the sample before of the hit's sign, above the threshold); the
            # flat or falling rest of a longer transient (a source's crossing) has none
            later = group[group >= max(peaks) + n_apart]
            onset = (r_time[later] - r_time[later - 1]) * np.sign(r_time[later])
            candidates = later[
                (np.abs(z[later]) > threshold_sigma * sigma)
                & (onset > threshold_sigma * math.sqrt(2) * sigma_sample)
            ]
    return events
