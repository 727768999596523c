"""How a recording's glitch events group: on the sky, where transients that recur at one
position are a source missing from the sky map (:func:`sky_fixed_groups`), and in time,
where events of several detectors at one sample are hits they share
(:func:`coincidences`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.stats

from ..model import unit_vectors

SEPARATE_CROSSINGS_S = 30.0  # events further apart in time are different crossings
# a source's fitted tail tau over the time its beam's FWHM takes to pass (a Gaussian
# crossing of 1 or 2.2 s FWHM fits tau = 0.28 and 0.31 of it); a cosmic ray's tail is its
# detector's and readout's response, a few samples (TOAST's hits: 0.05 s of 2.2 s)
SOURCE_TAU_PER_CROSSING = 0.15


def event_directions(events, pointings_ecl: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """(n_events, 3) ecliptic unit vectors where each event's detector looked at its time."""
    indices = [
        min(int(np.searchsorted(times_s, event.time_s - 1e-9)), times_s.size - 1)
        for event in events
    ]
    angles = np.array(
        [pointings_ecl[e.detector, i, :2] for e, i in zip(events, indices, strict=True)]
    ).reshape(-1, 2)
    return unit_vectors(angles[:, 0], angles[:, 1])[0]


def crossing_times_s(events, pointings_ecl: np.ndarray, times_s: np.ndarray, fwhm_arcmin):
    """(n_events,) the time the beam's FWHM takes to pass each event's position: the FWHM
    over the scan speed of its detector at its time [s]."""
    out = np.empty(len(events))
    for j, event in enumerate(events):
        i = min(int(np.searchsorted(times_s, event.time_s - 1e-9)), times_s.size - 2)
        step = pointings_ecl[event.detector, i : i + 2, :2]
        ends = unit_vectors(step[:, 0], step[:, 1])[0]
        angle_deg = math.degrees(math.acos(min(1.0, float(ends[0] @ ends[1]))))
        speed_deg_s = angle_deg / (times_s[i + 1] - times_s[i])
        out[j] = fwhm_arcmin / 60.0 / speed_deg_s if speed_deg_s > 0 else math.inf
    return out


def sky_fixed_groups(
    events, pointings_ecl: np.ndarray, times_s: np.ndarray, radius_arcmin: float
) -> list[list[int]]:
    """Indices of events that recur at one sky position: events as long as a source's
    crossing (a tail tau of at least SOURCE_TAU_PER_CROSSING times the time the beam's
    FWHM, ``radius_arcmin``, takes to pass) within ``radius_arcmin`` of each other on the
    sky (linked transitively), seen either on more than one crossing (times >
    SEPARATE_CROSSINGS_S apart) or by more than one detector with the same sign and
    amplitudes within a factor 2 (an intensity seen by each detector at its own pointing).
    A cosmic ray hits one detector (or the two of a pixel) once, at a random sky position,
    and lasts its detector's and readout's response; a source missing from the sky map is
    seen at its position each time a detector crosses it, for a beam's crossing."""
    crossing = crossing_times_s(events, pointings_ecl, times_s, radius_arcmin)
    long = [i for i, e in enumerate(events) if e.tau_s >= SOURCE_TAU_PER_CROSSING * crossing[i]]
    if len(long) < 2:
        return []
    return [
        [long[i] for i in group]
        for group in _positional_groups(
            [events[i] for i in long], pointings_ecl, times_s, radius_arcmin
        )
    ]


def _positional_groups(events, pointings_ecl, times_s, radius_arcmin) -> list[list[int]]:
    """:func:`sky_fixed_groups` without the duration test."""
    directions = event_directions(events, pointings_ecl, times_s)
    cos_radius = math.cos(math.radians(radius_arcmin / 60.0))
    parent = list(range(len(events)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    close = directions @ directions.T >= cos_radius
    for i, j in zip(*np.nonzero(np.triu(close, 1)), strict=True):
        parent[root(int(i))] = root(int(j))
    groups: dict[int, list[int]] = {}
    for i in range(len(events)):
        groups.setdefault(root(i), []).append(i)
    out = []
    for members in groups.values():
        times = np.sort([events[i].time_s for i in members])
        crossings = times.size > 1 and times[-1] - times[0] > SEPARATE_CROSSINGS_S
        if crossings or _alike_in_several_detectors([events[i] for i in members]):
            out.append(sorted(members, key=lambda i: events[i].time_s))
    return out


def _alike_in_several_detectors(events) -> bool:
    """Two or more detectors, each one's strongest event of the same sign and within a
    factor 2 of the others'."""
    strongest: dict[int, float] = {}
    for event in events:
        if abs(event.amplitude_k) > abs(strongest.get(event.detector, 0.0)):
            strongest[event.detector] = event.amplitude_k
    if len(strongest) < 2:
        return False
    values = np.array(list(strongest.values()))
    same_sign = np.all(values > 0) or np.all(values < 0)
    return bool(same_sign and np.abs(values).max() <= 2 * np.abs(values).min())


# events in different detectors whose first samples lie within this many samples of
# each other are one coincident event (the same hit resampled alike peaks at one sample)
COINCIDENCE_SAMPLES = 1
# the chance probability below which the coincidences are more than chance: 5 sigma, one-sided
COINCIDENCE_P_VALUE = 2.87e-7
# above it, and below this, the words say "more than chance but short of 5 sigma"
CHANCE_LIKE_P_VALUE = 1e-3


@dataclass(frozen=True)
class Coincidences:
    """Events shared across detectors (:func:`coincidences`): ``groups`` of event
    indices, each in two or more detectors within COINCIDENCE_SAMPLES; the detector
    pairs they make (``observed_pairs``) against those independent hits would make by
    chance (``expected_pairs``) and the Poisson probability of as many or more."""

    groups: list[list[int]]
    detectors: list[set[int]]  # each group's detectors
    observed_pairs: int
    expected_pairs: float
    p_value: float
    window_samples: int = COINCIDENCE_SAMPLES  # w: events within w samples are linked

    @property
    def significant(self) -> bool:
        """More coincidences than chance: p below COINCIDENCE_P_VALUE (5 sigma)."""
        return self.p_value < COINCIDENCE_P_VALUE


def coincidences(
    events, times_s: np.ndarray, valid: np.ndarray, window_samples: int = COINCIDENCE_SAMPLES
) -> Coincidences:
    """Coincident events and their chance rate.

    Events in different detectors within w = ``window_samples`` samples (a glitch's first
    sample: COINCIDENCE_SAMPLES; events timed less well, a wider w) are linked
    (transitively) into groups; a group of k detectors makes k(k-1)/2 detector pairs.
    Independent Poisson hits at n_i and n_j events over the T_ij both detectors keep
    (``valid``, (n_det, n)) coincide by chance n_i n_j (2w + 1) dt / T_ij times (dt / T_ij
    counted in samples); the sum over pairs is the expected number, and p = P(X >=
    observed) for X Poisson."""
    index = np.array([int(np.searchsorted(times_s, e.time_s - 1e-9)) for e in events], int)
    order = np.argsort(index, kind="stable")
    groups, current = [], []
    for i in order:
        if current and index[i] - index[current[-1]] > window_samples:
            groups.append(current)
            current = []
        current.append(int(i))
    if current:
        groups.append(current)
    by_group = [(g, {events[i].detector for i in g}) for g in groups]
    shared = [(g, d) for g, d in by_group if len(d) >= 2]
    observed = sum(len(d) * (len(d) - 1) // 2 for _, d in shared)
    counts = np.bincount([e.detector for e in events], minlength=valid.shape[0])
    hit = np.flatnonzero(counts)
    window = 2 * window_samples + 1
    expected = 0.0
    for a, i in enumerate(hit):
        for j in hit[a + 1 :]:
            both = int(np.count_nonzero(valid[i] & valid[j]))
            if both:
                expected += counts[i] * counts[j] * window / both
    p_value = float(scipy.stats.poisson.sf(observed - 1, expected)) if observed else 1.0
    return Coincidences(
        [g for g, _ in shared], [d for _, d in shared], observed, expected, p_value, window_samples
    )


def coincidence_sentence(found: Coincidences) -> str:
    """The coincidences in words: how many events are shared, by how many detectors,
    against chance."""
    if not found.groups:
        return "no event coincides in time with one in another detector"
    n_shared = sum(len(g) for g in found.groups)
    widest = max(len(d) for d in found.detectors)
    samples = "sample" if found.window_samples == 1 else "samples"
    chance = (
        f"{found.observed_pairs} detector pairs coincide within {found.window_samples} "
        f"{samples}, chance expects {found.expected_pairs:.2g} (p = {found.p_value:.2g})"
    )
    if found.significant:
        return (
            f"{n_shared} events are shared by detectors in {len(found.groups)} coincident "
            f"events of up to {widest} detectors: {chance}: hits shared by the detectors "
            "(a particle shower, or a hit on the wafer's substrate), not independent per "
            "detector"
        )
    if found.p_value < CHANCE_LIKE_P_VALUE:
        return (
            f"{len(found.groups)} coincidences, more than chance gives but short of 5 sigma "
            f"({chance})"
        )
    return f"{len(found.groups)} coincidences, as many as chance gives ({chance})"


def coincidence_groups(times_s, names) -> dict:
    """{"t = .. s": the detectors sharing the event at that time}: a coincidence scope's
    groups, labelled by their events' times [s]."""
    return {f"t = {t:.2f} s": list(n) for t, n in zip(times_s, names, strict=True)}


def coincidence_scope(found: Coincidences, events, detector_names) -> dict:
    """The scope of events that coincide across detectors more than chance: {"by":
    "coincidence", "groups": {"t = .. s": the detectors sharing that event}, "times_s":
    the events' times [s] in the groups' order, "observed_pairs", "expected_pairs",
    "p_value"} (``found``: :func:`coincidences`)."""
    times_s = [events[g[0]].time_s for g in found.groups]
    return {
        "by": "coincidence",
        "groups": coincidence_groups(
            times_s, [[detector_names[d] for d in sorted(ds)] for ds in found.detectors]
        ),
        "times_s": times_s,
        "observed_pairs": found.observed_pairs,
        "expected_pairs": found.expected_pairs,
        "p_value": found.p_value,
    }
