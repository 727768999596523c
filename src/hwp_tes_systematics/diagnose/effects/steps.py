"""Readout steps: a detector's offset and gain jumping at one time (a SQUID's flux jump, a
bias-line step, a readout reset). The event model, the scan that finds them in a residual,
the exact fit of each, and the catalog effect.

Detector k's recording after a step at t_s (the first sample after it):

    d_rec(t) = d(t) + H(t - t_s) [o + s d(t)],

o the offset jump [K], s the relative gain jump (dimensionless), d the detector's signal
(the nominal TOD d_nom: HWPSS, sky, dipole). The gain part is a jump of the 2f HWPSS
amplitude by s A_2 at t_s; the offset part a step in the low frequencies.

Scan (:func:`step_scan`): for every candidate t_s the Whittle fit of the two templates
T_o = H v and T_g = H c v (v the valid samples, c the part of d_nom above f_HWP / 2,
the carrier) to the residual R, each alone:

    delta chi^2(t_s) = <T_o, R>^2 / <T_o, T_o> + <T_g, R>^2 / <T_g, T_g>

with <a, b> = sum_f 2 Re(a_f* b_f) w_f (:mod:`..linalg`). <T, R> = n sum_t T(t) (W R)(t)
(W R = irfft(w R_f)), a cumulative sum over t >= t_s; <T_o, T_o> = n [L k_0 + 2 sum_{l<L}
(L - l) k_l] (k = irfft(w), L = n - t_s, the mask ignored); <T_g, T_g> ~ n w_c P (1 - P /
P_0), P = sum_{t>=t_s} c(t)^2 (w_c the weight at 2 f_HWP, where c lives; the factor: the
step's mean taken by the nominal 2f amplitude). The largest is then fitted exactly
(:func:`fit_step`: both templates with the mask, jointly with the linear templates fitted
beside them, on the samples around it) and kept when its delta chi^2 pays the BIC (ln N
per part, 2 ln N for the time: a change point's location); the search repeats on the
residual without it. The time's error is
from where the scan stays within 16 of its peak (:func:`time_sigma_s`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..fourier import irfft, rfft
from ..linalg import cross, solve_normal
from .base import Effect, format_temperature, register
from .event_groups import coincidence_sentence, coincidences

EDGE_S = 60.0  # no step is sought within this of a recording's ends (an edge is an offset)
MAX_STEPS = 4  # steps sought per detector
MAX_TRIES = 8  # candidates tried per detector (a smooth candidate is skipped)
# a step is compared with the linear changes over RAMP_S centred within RAMP_S of it: a
# readout step is one sample sharp, a drift or a modulation smooth over minutes. On
# simulated 20-min detectors: offset steps of 5-25 sigma beat the ramp by 20-100, gain
# steps of 5-15 sigma by 2-23, a 900-s modulation of the offset (3e-4 K) by -6 to 12, of
# the 2f amplitude (2 %) by less than -19,000
RAMP_S = 180.0
RAMP_CENTRES = 9  # the ramp's centres tried, evenly over +- RAMP_S
# the verdict on D (:func:`sharpness`): smooth below -this x 2 sqrt(E) (the candidate is
# dropped), sharp above +this x 2 sqrt(E), else a step not told apart from a ramp
SHARPNESS_SIGMAS = 1.0
# the step time's error: the span within TIME_LEVEL of the scan's peak, over its root
# (the span within 1 gives rms pulls of 8 and 12 on simulated steps) ...
TIME_LEVEL = 16.0
# and at least TIME_CUSP_SCALE over the delta chi^2 a step loses per sample it is moved
# (o^2 + s^2 <c^2>) / sigma^2 in white noise: the argmax of a random walk with that drift
# has a heavy-tailed error, 68 % within 3 and 99 % within 19-25 of this unit. The larger
# of the two, on 570 simulated offset and gain steps (5-50 sigma, knees 20 and 100 mHz):
# 68 % of the times within 0.5 of it, 2 % beyond 3 (heavy tails, not a Gaussian error)
TIME_CUSP_SCALE = 6.0
REFINE_SAMPLES = 1  # the exact fit tries the scan's time and this many samples each side
# the parts a step may have: an offset jump, a gain jump or both (each step takes the one
# of the three its BIC prefers; its count: the parts and its time)
PARTS = ("offset", "gain")
# the BIC's count for a step's time: a change point's location costs more than a regular
# parameter (the largest delta chi^2 of an offset step over a noise-only scan: 99 % below
# 17-23 for 20 min to 1 h at 19-31 Hz, reaching 2 ln N = 21-25; 3 ln N for a step of one
# part keeps a 64-detector wafer's chance of a false step near 1 %)
TIME_PARAMETERS = 2
CHOICES = (("offset",), ("gain",), PARTS)


@dataclass(frozen=True)
class StepEvent:
    """A step in detector ``detector`` at ``time_s`` (its first sample after the step):
    offset jump ``offset_k`` [K] and relative gain jump ``gain``."""

    detector: int
    time_s: float
    offset_k: float
    gain: float
    sigma_offset_k: float = 0.0
    sigma_gain: float = 0.0
    significance: float = 0.0  # sqrt(delta chi^2) of the step against none
    sigma_time_s: float = 0.0  # where delta chi^2 stays within 1 of its peak
    parts: tuple[str, ...] = ("offset", "gain")  # the parts fitted (the others are 0)
    sharp: bool = True  # False: not told apart from a change over RAMP_S (:func:`sharpness`)

    @property
    def n_parameters(self) -> int:
        """Its time (TIME_PARAMETERS) and each part fitted: the BIC's count."""
        return TIME_PARAMETERS + len(self.parts)


def step_tod(times_s: np.ndarray, signal: np.ndarray, events) -> np.ndarray:
    """sum of the steps' H(t - t_s) [o + s d(t)], (n_det, n), with d = ``signal`` (n_det, n)."""
    out = np.zeros_like(signal, dtype=float)
    for event in events:
        first = int(np.searchsorted(times_s, event.time_s - 1e-9))
        out[event.detector, first:] += event.offset_k + event.gain * signal[event.detector, first:]
    return out


def carrier(signal: np.ndarray, f_cut_hz: float, sampling_rate_hz: float) -> np.ndarray:
    """The part of a detector's signal above ``f_cut_hz`` (the HWPSS and its lines)."""
    n = signal.size
    spectrum = rfft(signal)
    spectrum[np.fft.rfftfreq(n, 1.0 / sampling_rate_hz) < f_cut_hz] = 0.0
    return irfft(spectrum, n=n)


def _box_norms(kernel: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """sum_{i, j < L} k_(i - j) for boxes of length L: L k_0 + 2 sum_{l < L} (L - l) k_l."""
    lags = np.arange(1, kernel.size)
    first = np.concatenate([[0.0], np.cumsum(kernel[1:])])  # sum_{l=1}^{m} k_l, m = 0..n-1
    moment = np.concatenate([[0.0], np.cumsum(lags * kernel[1:])])
    m = np.clip(lengths - 1, 0, kernel.size - 1)
    return lengths * kernel[0] + 2.0 * (lengths * first[m] - moment[m])


def step_scan(
    r_f: np.ndarray, w: np.ndarray, valid: np.ndarray, carrier_k: np.ndarray, w_carrier: float
) -> dict[str, np.ndarray]:
    """{"offset", "gain"}: delta chi^2 of each part of a step at every sample (module
    docstring: each template alone)."""
    n = valid.size
    weighted = irfft(w * r_f, n=n) * valid
    after = np.cumsum(weighted[::-1])[::-1]  # sum_{t >= t_s}
    lengths = n - np.arange(n)
    offset_norm = n * _box_norms(irfft(w, n=n), lengths)
    good = offset_norm > 1e-12 * max(offset_norm.max(), 1e-300)
    offset_chi2 = np.zeros(n)
    offset_chi2[good] = (n * after[good]) ** 2 / offset_norm[good]
    # both parts projected off the carrier itself (the nominal 2f amplitude takes the
    # step's mean): T_g - (P / P_0) c
    gain_after = np.cumsum((carrier_k * weighted)[::-1])[::-1]
    power_after = np.cumsum((carrier_k**2 * valid)[::-1])[::-1]
    fraction = power_after / max(power_after[0], 1e-300)
    gain_projected = gain_after - fraction * gain_after[0]
    gain_norm = n * w_carrier * power_after * (1.0 - fraction)
    good = gain_norm > 1e-12 * max(gain_norm.max(), 1e-300)
    gain_chi2 = np.zeros(n)
    gain_chi2[good] = (n * gain_projected[good]) ** 2 / gain_norm[good]
    return {"offset": offset_chi2, "gain": gain_chi2}


@dataclass(frozen=True)
class Bank:
    """The linear templates fitted beside the steps, for one detector: their rfft rows
    (n_rows, nf) and the pseudo-inverse of their Gram matrix."""

    rows: np.ndarray
    gram_inverse: np.ndarray

    @classmethod
    def of(cls, rows: np.ndarray | None, gram: np.ndarray | None) -> Bank | None:
        if rows is None or gram is None or rows.shape[0] == 0:
            return None
        return cls(rows, solve_normal(gram, np.zeros(gram.shape[0]))[1])


def fit_step(
    r_f: np.ndarray,
    w: np.ndarray,
    valid: np.ndarray,
    signal_k: np.ndarray,
    times_s: np.ndarray,
    index: int,
    detector: int,
    bank: Bank | None = None,
    parts: tuple[str, ...] = PARTS,
) -> tuple[StepEvent, np.ndarray]:
    """The exact Whittle fit of the step's ``parts`` (o, s or both) at sample ``index`` (and the
    REFINE_SAMPLES around it, the best kept), jointly with the ``bank`` of linear templates
    fitted beside it (the step's templates projected off them: T' = T - B G^+ <B, T>, the
    Schur complement): the event and the rfft of the change the step makes to the joint
    model (T' times its values)."""
    n = valid.size
    bank_r = cross(bank.rows, r_f, w) if bank is not None else None
    best = None
    for i in range(max(1, index - REFINE_SAMPLES), min(n - 1, index + REFINE_SAMPLES + 1)):
        if not valid[i]:
            continue
        fitted = fit_edge(r_f, w, valid, signal_k, edge_shape(n, i), parts, bank, bank_r)
        if best is None or fitted[0] > best[0]:
            best = (*fitted, i)
    delta_chi2, values, covariance, change_f, i = best
    sigmas = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    fitted = dict(zip(parts, zip(values, sigmas, strict=True), strict=True))
    offset, sigma_offset = fitted.get("offset", (0.0, 0.0))
    gain, sigma_gain = fitted.get("gain", (0.0, 0.0))
    event = StepEvent(
        detector=detector,
        time_s=float(times_s[i]),
        offset_k=float(offset),
        gain=float(gain),
        sigma_offset_k=float(sigma_offset),
        sigma_gain=float(sigma_gain),
        significance=math.sqrt(max(delta_chi2, 0.0)),
        parts=tuple(parts),
    )
    return event, change_f


def sharpness(r_f, w, valid, signal_k, index, width, parts, values, bank) -> tuple[float, float]:
    """(D, E) of the step at ``index`` of fitted ``values``: D its delta chi^2 less that of
    the best linear change of ``parts`` over ``width`` samples centred at RAMP_CENTRES
    points within ``width`` of it, E = ||values (T_step - T_ramp)||^2 at its own centre
    (the step's information above 1 / width). A step gives D ~ +E +- 2 sqrt(E), a smooth
    change D ~ -E +- 2 sqrt(E)."""
    n = valid.size
    step = fit_edge(r_f, w, valid, signal_k, edge_shape(n, index), parts, bank)[0]
    centres = np.clip(np.linspace(index - width, index + width, RAMP_CENTRES).astype(int), 0, n - 1)
    ramp = max(
        fit_edge(r_f, w, valid, signal_k, edge_shape(n, int(c), width), parts, bank)[0]
        for c in centres
    )
    difference = edge_shape(n, index) - edge_shape(n, index, width)
    shapes = {"offset": difference, "gain": difference * signal_k}
    templates = rfft(np.stack([shapes[part] for part in parts]) * valid)
    change_f = np.asarray(values) @ templates
    return step - ramp, float(cross(change_f[None], change_f, w)[0])


def edge_shape(n: int, index: int, width_samples: float = 0.0) -> np.ndarray:
    """H(t - t_index) (``width_samples`` 0), or a linear ramp from 0 to 1 over
    ``width_samples`` centred on it: a step, or the smooth change it is tested against."""
    if width_samples <= 0:
        shape = np.zeros(n)
        shape[index:] = 1.0
        return shape
    return np.clip((np.arange(n) - index) / width_samples + 0.5, 0.0, 1.0)


def fit_edge(r_f, w, valid, signal_k, shape, parts, bank: Bank | None, bank_r=None):
    """The Whittle fit of ``parts`` with the edge ``shape`` (offset: shape; gain: shape d),
    jointly with ``bank``: (delta chi^2, values, covariance, the rfft of its change to the
    joint model)."""
    shapes = {"offset": shape, "gain": shape * signal_k}
    templates = rfft(np.stack([shapes[part] for part in parts]) * valid)
    gram = cross(templates, templates, w)
    rhs = cross(templates, r_f, w)
    if bank is not None:  # projected off the bank: the Schur complement
        bank_r = cross(bank.rows, r_f, w) if bank_r is None else bank_r
        bank_t = cross(bank.rows, templates, w)  # <B, T>
        projection = bank.gram_inverse @ bank_t  # G^+ <B, T>
        gram = gram - bank_t.T @ projection
        rhs = rhs - projection.T @ bank_r
    values, covariance = solve_normal(gram, rhs)
    change_f = values @ templates
    if bank is not None:  # the bank's coefficients move by -G^+ <B, T> values
        change_f = change_f - (projection @ values) @ bank.rows
    return float(values @ rhs), values, covariance, change_f


def time_sigma_s(scan: np.ndarray, index: int, sampling_rate_hz: float) -> float:
    """The step time's error: half the span around the peak at ``index`` where the scan's
    delta chi^2 stays within TIME_LEVEL of it, over sqrt(TIME_LEVEL) (at least half a
    sample). A change point's likelihood is a noisy cusp, not a parabola: the span within
    1 of the peak is far too narrow (:data:`TIME_CUSP_SCALE` for the calibration)."""
    inside = scan >= scan[index] - TIME_LEVEL
    lo = index
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = index
    while hi < scan.size - 1 and inside[hi + 1]:
        hi += 1
    return max(0.5, 0.5 * (hi - lo) / math.sqrt(TIME_LEVEL)) / sampling_rate_hz


def find_steps(
    r_f: np.ndarray,
    w: np.ndarray,
    valid: np.ndarray,
    signal_k: np.ndarray,
    times_s: np.ndarray,
    detector: int,
    f_hwp_hz: float,
    ln_n: float,
    bank: Bank | None = None,
) -> list[StepEvent]:
    """The steps in one detector's residual (rfft ``r_f``, weights ``w`` = v / S_f on the
    fitted modes): the scan's best, its parts (offset, gain or both) those whose delta
    chi^2 pays most beyond the BIC (ln N per part, TIME_PARAMETERS ln N for its time),
    fitted exactly (jointly with ``bank``), while that pays; dropped when a linear change
    over RAMP_S near it fits clearly better (:func:`sharpness`; those samples are then
    skipped), marked not sharp when neither is clearly better; at most MAX_STEPS, none
    within EDGE_S of the ends."""
    n = valid.size
    fs = 1.0 / (times_s[1] - times_s[0])
    carrier_k = carrier(signal_k, 0.5 * f_hwp_hz, fs)
    freqs = np.fft.rfftfreq(n, 1.0 / fs)
    near = np.abs(freqs - 2 * f_hwp_hz) < 0.1 * f_hwp_hz
    w_carrier = float(np.median(w[near])) if near.any() else float(np.median(w[w > 0]))
    # 1 / sigma^2 per sample of the white noise (E|R_f|^2 = n sigma^2 there)
    white_weight = n * float(np.median(w[freqs > 0.25 * freqs[-1]]))
    edge = int(EDGE_S * fs)
    allowed = valid.copy()
    allowed[:edge] = False
    allowed[n - edge :] = False
    if not allowed.any():
        return []
    residual = r_f.copy()
    events = []
    for _ in range(MAX_TRIES):
        if len(events) == MAX_STEPS:
            break
        scans = step_scan(residual, w, valid, carrier_k, w_carrier)
        scans = {part: np.where(allowed, scan, 0.0) for part, scan in scans.items()}
        best = None  # (delta BIC, parts, index, their scan)
        for parts in CHOICES:
            scan = sum(scans[part] for part in parts)
            index = int(np.argmax(scan))
            delta_bic = scan[index] - (TIME_PARAMETERS + len(parts)) * ln_n
            if best is None or delta_bic > best[0]:
                best = (delta_bic, parts, index, scan)
        delta_bic, parts, index, scan = best
        if delta_bic < 0:
            break
        event, model_f = fit_step(
            residual, w, valid, signal_k, times_s, index, detector, bank, parts
        )
        if event.significance**2 < event.n_parameters * ln_n:
            break
        first = int(np.searchsorted(times_s, event.time_s - 1e-9))
        width = int(RAMP_S * fs)
        values = [event.offset_k if p == "offset" else event.gain for p in parts]
        d, e = sharpness(residual, w, valid, signal_k, first, width, parts, values, bank)
        if d < -SHARPNESS_SIGMAS * 2 * math.sqrt(e):  # smooth: a drift, a modulation
            allowed[max(0, first - width) : first + width] = False
            continue
        sharp = d > SHARPNESS_SIGMAS * 2 * math.sqrt(e)  # else not told apart from a ramp
        # the cusp's own scale: C / (delta chi^2 lost per sample moved), white noise
        rate = (event.offset_k**2 + event.gain**2 * np.mean(carrier_k**2)) * white_weight
        sigma_t = max(
            time_sigma_s(np.where(allowed, scan, -np.inf), index, fs),
            TIME_CUSP_SCALE / max(rate, 1e-300) / fs,
        )
        events.append(StepEvent(**{**event.__dict__, "sigma_time_s": sigma_t, "sharp": sharp}))
        residual = residual - model_f
    return events


@register
class ReadoutSteps(Effect):
    """Readout steps: d -> d + H(t - t_s) [o + s d] per detector and step.

    A SQUID's flux jump moves the offset (o); a step of the TES bias or of the readout's
    gain moves the responsivity (s), seen as a jump of the 2f HWPSS amplitude by s A_2.
    Found by a scan of the residual over the step's time (both parts, noise-weighted),
    fitted exactly at the best time, its parts (offset, gain or both) those the BIC
    prefers, kept while each pays ln N per part and 2 ln N for its time.
    """

    name = "readout_steps"
    title = "readout steps (offset and gain jumps)"
    parameters: ClassVar[dict[str, str]] = {"offset": "K", "gain": "", "time": "s"}
    events: ClassVar[bool] = True
    main_parameters = ("offset", "gain")
    kind = "events"
    stage = "events"
    signature = (
        "the offset and the 2f HWPSS amplitude jumping at one time and staying there, "
        "in one detector or in the detectors of one bias line at once"
    )
    discrimination = (
        "a gain drift (gain_drift) moves the 2f amplitude smoothly over the recording, a "
        "step at one sample; a gain fluctuation (gain_fluctuations) is a random walk of "
        "many small moves, a step one move the scan localises; a glitch decays back, a "
        "step stays; 1/f noise has no preferred time, a step's delta chi^2 peaks at one"
    )

    def find(self, problem, k: int, r_f: np.ndarray, bank=None, gram=None) -> list[StepEvent]:
        """The steps in detector k's residual ``r_f`` (:func:`find_steps` with the
        problem's weights and ln N_eff), fitted jointly with the linear templates ``bank``
        (rfft rows) of Gram matrix ``gram``."""
        ctx = problem.ctx
        return find_steps(
            r_f,
            problem.w_nom[k],
            problem.valid[k],
            ctx.d_nom[k],
            ctx.times_s,
            k,
            f_hwp_hz=_f_hwp_hz(ctx),
            ln_n=problem.ln_n_eff,
            bank=Bank.of(bank, gram),
        )

    @staticmethod
    def detector_events(ctx, events) -> list:
        return events

    @staticmethod
    def events_tod(ctx, events) -> np.ndarray:
        """The steps' TOD on the nominal signal, (n_det, n): :func:`step_tod`."""
        return step_tod(ctx.times_s, ctx.d_nom, events)

    def reported_parameters(self, fit, detector_names, sampling_rate_hz, units) -> dict:
        """Per step i: "step<i>.offset|gain|time[<detector>]" (the parts it was fitted
        with, and its time), in detector and time order."""
        out = {}
        for i, e in enumerate(sorted(fit.events, key=lambda e: (e.detector, e.time_s))):
            det = detector_names[e.detector]
            values = {
                "offset": (e.offset_k, e.sigma_offset_k, "K"),
                "gain": (e.gain, e.sigma_gain, ""),
                "time": (e.time_s, max(e.sigma_time_s, 0.5 / sampling_rate_hz), "s"),
            }
            for parameter in (*e.parts, "time"):
                value, sigma, unit = values[parameter]
                out[f"step{i}.{parameter}[{det}]"] = {
                    "value": value,
                    "sigma": sigma,
                    "unit": unit,
                    "detector": det,
                    "parameter": parameter,
                }
        return out

    def apply(self, ctx, params, tod=None):
        """``params``: {"events": [(detector, time_s, offset_k, gain), ...]}; the gain
        multiplies ``tod`` (default d_nom) itself."""
        tod = ctx.d_nom if tod is None else tod
        events = [e if isinstance(e, StepEvent) else StepEvent(*e) for e in params["events"]]
        return tod + step_tod(ctx.times_s, tod, events)

    def evidence(self, ev, fit) -> str:
        events = fit.events
        if not events:
            return "no step left after the fit"
        names = ev.ctx.detector_names
        strongest = max(events, key=lambda e: e.significance)

        def described(e) -> str:
            said = []
            if "offset" in e.parts and e.sigma_offset_k > 0:
                said.append(
                    f"offset {format_temperature(e.offset_k)} "
                    f"({abs(e.offset_k) / e.sigma_offset_k:.0f} sigma)"
                )
            if "gain" in e.parts and e.sigma_gain > 0:
                said.append(f"gain {e.gain:+.2e} ({abs(e.gain) / e.sigma_gain:.0f} sigma)")
            return (
                f"{names[e.detector]} at t = {e.time_s:.1f} +- {e.sigma_time_s:.1g} s: "
                + ", ".join(said)
            )

        listed = "; ".join(described(e) for e in sorted(events, key=lambda e: -e.significance)[:5])
        return (
            f"{len(events)} step(s), the strongest {strongest.significance:.0f} sigma: {listed}; "
            "each stays after its time (no decay)"
            + (
                "; " + coincidence_sentence(step_coincidences(events, ev.ctx))
                if len(names) > 1
                else ""
            )
        )

    def scope(self, ctx, fit=None) -> dict:
        """Per detector, or by coincidence where steps of several detectors share a time
        more than chance (a bias line's step): as the glitches' scope."""
        if fit is None or ctx.n_detectors < 2 or not fit.events:
            return super().scope(ctx)
        found = step_coincidences(fit.events, ctx)
        if not found.significant:
            return super().scope(ctx)
        names = ctx.detector_names
        return {
            "by": "coincidence",
            "groups": {
                f"t = {fit.events[g[0]].time_s:.2f} s": [names[d] for d in sorted(detectors)]
                for g, detectors in zip(found.groups, found.detectors, strict=True)
            },
            "observed_pairs": found.observed_pairs,
            "expected_pairs": found.expected_pairs,
            "p_value": found.p_value,
        }


def step_coincidences(events, ctx):
    """:func:`.event_groups.coincidences` of steps, linked within 3 sqrt(2) times the
    largest step time error (a step is timed to its scan's cusp, not to a sample)."""
    widest_s = max(e.sigma_time_s for e in events)
    window = max(1, math.ceil(3 * math.sqrt(2) * widest_s * ctx.sampling_rate_hz))
    return coincidences(events, ctx.times_s, ctx.valid, window)


def _f_hwp_hz(ctx) -> float:
    """The HWP's rotation frequency from its angle: d chi / dt / 2 pi."""
    chi = np.unwrap(ctx.hwp_angle_rad)
    return float(abs(chi[-1] - chi[0]) / (ctx.times_s[-1] - ctx.times_s[0]) / (2 * math.pi))
