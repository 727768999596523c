"""The search for readout steps in one detector's residual: the scan's best candidates
(:mod:`.step_scan`), each tested for sharpness, fitted exactly (:mod:`.step_fit`: both
parts with the mask, jointly with the linear templates fitted beside them) and kept while
its delta chi^2 pays the BIC (ln N per part, TIME_PARAMETERS ln N for its time: a change
point's location); the search repeats on the residual without it. The time's error is
from where the scan stays within TIME_LEVEL of its peak (:func:`time_sigma_s`). Where
detectors step together beyond chance (a bias line), :mod:`.step_lines` puts them at one
time and fits the others there. :mod:`.steps` is the catalog effect.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..fourier import irfft, rfft
from ..linalg import cross
from .step_fit import Bank, TemplateFit, position_fits
from .step_scan import (
    PARTS,
    RAMP_S,
    ScanNorms,
    carrier,
    offset_norms,
    ramp_offset_terms,
    scan_weighted,
    sharpness,
)

EDGE_S = 60.0  # no step is sought within this of a recording's ends (an edge is an offset)
MAX_STEPS = 4  # steps sought per detector
MAX_TRIES = 8  # candidates tried per detector (a smooth candidate is skipped)
# the search in a detector stops at this many smooth candidates: its residual's largest
# changes are then another effect's (a drift, a modulation), fitted before any step
MAX_SMOOTH = 3
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
# the BIC's count for a step's time: a change point's location costs more than a regular
# parameter (the largest delta chi^2 of an offset step over a noise-only scan: 99 % below
# 17-23 for 20 min to 1 h at 19-31 Hz, reaching 2 ln N = 21-25; 3 ln N for a step of one
# part keeps a 64-detector wafer's chance of a false step near 1 %)
TIME_PARAMETERS = 2
# steps of a detector within RAMP_S of each other whose net change is below this fraction
# of the largest come back: a transient (a compact source crossed in 7 s is fitted by
# steps of +0.65 and -0.76 mK), not steps (:func:`without_returns`)
RETURN_FRACTION = 0.25


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
    # its time is its bias line's, counted in the line's strongest step (.step_lines)
    shared_time: bool = False
    # found only at its line's time, too weak at an unknown one (.step_lines)
    completed: bool = False

    @property
    def n_parameters(self) -> int:
        """Its time (TIME_PARAMETERS, none when shared) and each part fitted: the BIC's
        count."""
        return (0 if self.shared_time else TIME_PARAMETERS) + len(self.parts)


def step_tod(times_s: np.ndarray, signal: np.ndarray, events) -> np.ndarray:
    """sum of the steps' H(t - t_s) [o + s d(t)], (n_det, n), with d = ``signal`` (n_det, n)."""
    out = np.zeros_like(signal, dtype=float)
    for event in events:
        first = int(np.searchsorted(times_s, event.time_s - 1e-9))
        out[event.detector, first:] += event.offset_k + event.gain * signal[event.detector, first:]
    return out


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
    refine: int = REFINE_SAMPLES,
) -> tuple[StepEvent, np.ndarray]:
    """The exact Whittle fit of the step's ``parts`` (o, s or both) at sample ``index`` (and the
    ``refine`` samples around it, the best kept), jointly with the ``bank`` of linear templates
    fitted beside it (the step's templates projected off them: T' = T - B G^+ <B, T>, the
    Schur complement): the event and the rfft of the change the step makes to the joint
    model (T' times its values)."""
    n = valid.size
    positions = [
        i for i in range(max(1, index - refine), min(n - 1, index + refine + 1)) if valid[i]
    ] or [index]
    fits = position_fits(r_f, w, valid, signal_k, positions, bank, parts)
    j = max(range(len(positions)), key=lambda j: fits[j].delta_chi2)
    event = event_of(fits[j], float(times_s[positions[j]]), detector, parts)
    return event, fits[j].change_f()


def event_of(fit: TemplateFit, time_s: float, detector: int, parts: tuple[str, ...]) -> StepEvent:
    """The :class:`StepEvent` of one of :func:`position_fits`' fits at ``time_s``: each
    part's value with the root of its variance."""
    sigmas = np.sqrt(np.clip(np.diag(fit.covariance), 0.0, None))
    fitted = dict(zip(parts, zip(fit.values, sigmas, strict=True), strict=True))
    offset, sigma_offset = fitted.get("offset", (0.0, 0.0))
    gain, sigma_gain = fitted.get("gain", (0.0, 0.0))
    return StepEvent(
        detector=detector,
        time_s=time_s,
        offset_k=float(offset),
        gain=float(gain),
        sigma_offset_k=float(sigma_offset),
        sigma_gain=float(sigma_gain),
        significance=math.sqrt(max(fit.delta_chi2, 0.0)),
        parts=tuple(parts),
    )


def time_sigma_s(scan: np.ndarray, index: int, sampling_rate_hz: float) -> float:
    """The step time's error: half the span around the peak at ``index`` where the scan's
    delta chi^2 stays within TIME_LEVEL of it, over sqrt(TIME_LEVEL) (at least half a
    sample). A change point's likelihood is a noisy cusp, not a parabola: the span within
    1 of the peak is far too narrow (:data:`TIME_CUSP_SCALE` for the calibration)."""
    lo, hi = _span_within(scan, index, TIME_LEVEL)
    return max(0.5, 0.5 * (hi - 1 - lo) / math.sqrt(TIME_LEVEL)) / sampling_rate_hz


@dataclass(frozen=True)
class StepSearch:
    """What a detector's search needs that depends on its weights and signal only, not
    on the residual: computed once per detector and noise model (:meth:`of`)."""

    w: np.ndarray
    valid: np.ndarray
    signal_k: np.ndarray
    times_s: np.ndarray
    white_weight: float  # 1 / sigma^2 per sample of the white noise
    edge: int  # samples left out at each end (EDGE_S)
    half: int  # the ramps' half width [samples] (RAMP_S / 2)
    norms: ScanNorms  # the scan's, with the mask
    norms_unmasked: ScanNorms  # without it (the same where every sample is valid)
    offset_terms: tuple[float, float]  # :func:`ramp_offset_terms`

    def rate(self, event: StepEvent) -> float:
        """The delta chi^2 ``event`` loses per sample it is moved, in white noise:
        (o^2 + s^2 <c^2>) / sigma^2."""
        carrier_power = float(np.mean(self.norms.carrier_k**2))
        return (event.offset_k**2 + event.gain**2 * carrier_power) * self.white_weight

    @classmethod
    def of(cls, w, valid, signal_k, times_s, f_hwp_hz: float) -> StepSearch:
        n = valid.size
        fs = 1.0 / (times_s[1] - times_s[0])
        freqs = np.fft.rfftfreq(n, 1.0 / fs)
        near = np.abs(freqs - 2 * f_hwp_hz) < 0.1 * f_hwp_hz
        half = max(1, int(0.5 * RAMP_S * fs))
        carrier_k = carrier(signal_k, 0.5 * f_hwp_hz, fs)
        w_carrier = float(np.median(w[near])) if near.any() else float(np.median(w[w > 0]))
        unprojected = offset_norms(w, n)
        norms = ScanNorms.of(w, valid, carrier_k, w_carrier, unprojected if valid.all() else None)
        return cls(
            w=w,
            valid=valid,
            signal_k=signal_k,
            times_s=times_s,
            # E|R_f|^2 = n sigma^2 in the white noise
            white_weight=n * float(np.median(w[freqs > 0.25 * freqs[-1]])),
            edge=int(EDGE_S * fs),
            half=half,
            norms=norms,
            norms_unmasked=norms
            if valid.all()
            else ScanNorms.of(w, np.ones(n, bool), carrier_k, w_carrier, unprojected),
            offset_terms=ramp_offset_terms(w, n, n // 2, half),
        )

    def bank(self, rows: np.ndarray | None = None, gram: np.ndarray | None = None) -> Bank:
        """The :class:`Bank` of the linear templates ``rows`` (rfft, Gram matrix ``gram``)
        fitted beside the steps, with the recording's trend; without ``rows``, where samples
        are flagged, with the gap offset v too (the scan's nuisance templates; a fit's
        rows hold it among the nominal model's)."""
        if rows is None and not self.valid.all():
            rows = rfft(self.valid * 1.0)[None]
            gram = cross(rows, rows, self.w)
        return Bank.of(rows, gram, self.norms.trend_f, self.w, self.valid.size)


def choose_parts(scans: dict[str, np.ndarray], ln_n: float) -> tuple:
    """(delta BIC, parts, sample, their scan) of the best candidate: the part whose scan
    pays most beyond its BIC (TIME_PARAMETERS + 1 ln N) at its peak, and the other part
    beside it; where neither part alone pays, both at the peak of their sum.

    The other part joins where it pays its ln N at the first's sample, or where it pays a
    step's whole BIC at its own peak within the first's time error (the span where the
    first's scan stays within TIME_LEVEL of its peak); where that is its own peak and a
    sharper one (its span within TIME_LEVEL narrower than the first's), both parts go to
    it: a weak gain part's scan is broad, its peak tens of seconds from an offset step's
    time, where the offset part alone would be a ramp's edge, smooth. Not the peak of the
    parts' sum: the broad part's scan, rising over the sharp part's error, moves it off
    the edge (by 11 samples in a bias line's step on TOAST's noise); nor the other part's
    peak over a weak step's time error where it does not pay a step's BIC: that is its
    largest noise (4 sigma offsets beside gain steps on TOAST's 1/f noise)."""
    singles = []
    for part in PARTS:
        index = int(np.argmax(scans[part]))
        singles.append((scans[part][index] - (TIME_PARAMETERS + 1) * ln_n, (part,), index))
    delta_bic, parts, index = max(singles, key=lambda c: c[0])
    both = sum(scans.values())
    if delta_bic < 0:
        index = int(np.argmax(both))
        return both[index] - (TIME_PARAMETERS + 2) * ln_n, PARTS, index, both
    (first,) = parts
    (other,) = (part for part in PARTS if part != first)
    lo, hi = _span_within(scans[first], index, TIME_LEVEL)
    sharper = lo + int(np.argmax(scans[other][lo:hi]))  # the other part's peak there
    if scans[other][sharper] >= (TIME_PARAMETERS + 1) * ln_n:
        other_lo, other_hi = _span_within(scans[other], sharper, TIME_LEVEL)
        own_peak = other_lo + int(np.argmax(scans[other][other_lo:other_hi])) == sharper
        if own_peak and other_hi - other_lo < hi - lo:
            index = sharper  # its own peak, within the first's error: the step's time
        return both[index] - (TIME_PARAMETERS + 2) * ln_n, PARTS, index, both
    if scans[other][index] > ln_n:
        return delta_bic + scans[other][index] - ln_n, PARTS, index, both
    return delta_bic, parts, index, scans[first]


def _span_within(scan: np.ndarray, index: int, level: float) -> tuple[int, int]:
    """[lo, hi): the samples around ``index`` where ``scan`` stays within ``level`` of
    its value there."""
    inside = scan >= scan[index] - level
    lo = index
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = index + 1
    while hi < scan.size and inside[hi]:
        hi += 1
    return lo, hi


def find_steps(
    r_f: np.ndarray,
    search: StepSearch,
    detector: int,
    ln_n: float,
    bank: Bank | None = None,
) -> list[StepEvent]:
    """The steps in one detector's residual (rfft ``r_f``; ``search`` its weights
    w = v / S_f on the fitted modes, signal and what depends on them): the scan's best, its parts
    (offset, gain or both) those whose delta chi^2 pays most beyond the BIC (ln N per part,
    TIME_PARAMETERS ln N for its time); dropped when a linear change over RAMP_S near it
    fits clearly better (:func:`sharpness`; those samples are then skipped), else fitted
    exactly (jointly with ``bank``) and kept while that pays, marked not sharp when
    neither is clearly better; at most MAX_STEPS, none within EDGE_S of the ends."""
    w, valid, times_s = search.w, search.valid, search.times_s
    n = valid.size
    fs = 1.0 / (times_s[1] - times_s[0])
    edge, half = search.edge, search.half
    if n - 2 * edge < 4 * half:  # too short to tell a step from a change over RAMP_S
        return []
    allowed = valid.copy()
    allowed[:edge] = False
    allowed[n - edge :] = False
    if not allowed.any():
        return []
    bank = search.bank() if bank is None else bank
    residual = r_f.copy()
    events = []
    smooth = 0  # candidates found smooth
    for _ in range(MAX_TRIES):
        if len(events) == MAX_STEPS:
            break
        weighted = irfft(w * residual, n=n)
        parts_scan = scan_weighted(weighted, search.norms)
        scans = {part: parts_scan.chi2(part) * allowed for part in PARTS}
        delta_bic, parts, index, scan = choose_parts(scans, ln_n)
        if delta_bic < 0:
            break
        # the sharpness from a scan without the mask, as its norms are: the masked
        # projections beside them misjudge a step by hundreds where flags lie far away
        whole = parts_scan if valid.all() else scan_weighted(weighted, search.norms_unmasked)
        d, e = sharpness(whole, index, half, parts, (edge, n - edge), search.offset_terms)
        if d < -SHARPNESS_SIGMAS * 2 * math.sqrt(e):  # smooth: a drift, a modulation
            smooth += 1
            if smooth == MAX_SMOOTH:
                break
            allowed[max(0, index - 2 * half) : index + 2 * half] = False
            continue
        event, model_f = fit_step(
            residual, w, valid, search.signal_k, times_s, index, detector, bank, parts
        )
        if event.significance**2 < event.n_parameters * ln_n:
            break
        sharp = d > SHARPNESS_SIGMAS * 2 * math.sqrt(e)  # else not told apart from a ramp
        # the cusp's own scale: C / (delta chi^2 lost per sample moved), white noise
        sigma_t = max(
            time_sigma_s(np.where(allowed, scan, -np.inf), index, fs),
            TIME_CUSP_SCALE / max(search.rate(event), 1e-300) / fs,
        )
        events.append(StepEvent(**{**event.__dict__, "sigma_time_s": sigma_t, "sharp": sharp}))
        residual = residual - model_f
    return without_returns(events)


def without_returns(events: list[StepEvent]) -> list[StepEvent]:
    """``events`` less each cluster of a detector's steps (each within RAMP_S of the
    next) whose net change comes back: each part's sum within 3 sigma of 0 or within
    RETURN_FRACTION of its largest step. A step stays; a level that comes back is a
    transient (a source crossed, a glitch's shape), not steps."""
    dropped: set[int] = set()
    order = sorted(range(len(events)), key=lambda k: (events[k].detector, events[k].time_s))
    cluster: list[int] = []
    for k in [*order, None]:
        if cluster and (
            k is None
            or events[k].detector != events[cluster[-1]].detector
            or events[k].time_s - events[cluster[-1]].time_s > RAMP_S
        ):
            if len(cluster) > 1 and _comes_back([events[c] for c in cluster]):
                dropped |= set(cluster)
            cluster = []
        if k is not None:
            cluster.append(k)
    return [event for k, event in enumerate(events) if k not in dropped]


def _comes_back(steps: list[StepEvent]) -> bool:
    """Each part's net change within 3 sigma of 0 or RETURN_FRACTION of its largest step."""
    for values, sigmas in (
        ([e.offset_k for e in steps], [e.sigma_offset_k for e in steps]),
        ([e.gain for e in steps], [e.sigma_gain for e in steps]),
    ):
        net, sigma = abs(sum(values)), math.sqrt(sum(x**2 for x in sigmas))
        if net > max(3 * sigma, RETURN_FRACTION * max(abs(x) for x in values)):
            return False
    return True
