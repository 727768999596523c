"""A bias line's steps: where detectors step together beyond chance, the line stepped at
one time. :func:`line_time` puts the group's steps at the sample where their delta
chi^2, summed over detectors, peaks; :func:`steps_at_shared_time` fits every other
detector at that time and keeps a step where its parts alone pay (its time the line's,
not counted). The search in one detector is :mod:`.step_search`.
"""

from __future__ import annotations

import numpy as np

from .step_fit import Bank, position_fits
from .step_scan import PARTS
from .step_search import (
    TIME_CUSP_SCALE,
    TIME_LEVEL,
    StepEvent,
    StepSearch,
    event_of,
    fit_step,
    time_sigma_s,
)


def steps_at_shared_time(
    residual_f: np.ndarray,
    search: StepSearch,
    detector: int,
    line: StepEvent,
    ln_n: float,
    bank: Bank | None = None,
) -> StepEvent | None:
    """A step in detector ``detector`` at the time of ``line`` (the strongest step of a
    group of detectors stepping together beyond chance: a bias line), with its parts:
    fitted exactly at that sample (:func:`fit_step`) in the residual without the
    detector's own steps, kept where its delta chi^2 pays ln N per part, its time not
    counted (it is the line's, with the line's error). None where it does not pay, or the
    time is flagged or within EDGE_S of the ends in this detector."""
    index = int(np.searchsorted(search.times_s, line.time_s - 1e-9))
    n = search.valid.size
    if not (search.edge <= index < n - search.edge) or not search.valid[index]:
        return None
    event, _ = fit_step(
        residual_f,
        search.w,
        search.valid,
        search.signal_k,
        search.times_s,
        index,
        detector,
        search.bank() if bank is None else bank,
        line.parts,
        refine=0,
    )
    if event.significance**2 < len(line.parts) * ln_n:
        return None
    shared = {"sigma_time_s": line.sigma_time_s, "sharp": line.sharp}
    shared |= {"shared_time": True, "completed": True}
    return StepEvent(**{**event.__dict__, **shared})


# samples each side of a bias line's steps searched for the line's one time: from the
# earliest of its steps within LINE_SPAN of the strongest to the latest
LINE_WINDOW = 8
LINE_SPAN = 32


def line_time(members: list[tuple], fs: float) -> list[StepEvent]:
    """A bias line's steps at one time. ``members``: (event, residual rfft with that step in
    it and without the detector's other steps, :class:`StepSearch`, :class:`Bank` or None)
    per detector of a group stepping together. The line's sample is where the members'
    delta chi^2, summed over detectors, peaks (each refitted at every sample from
    LINE_WINDOW before the earliest member's step to LINE_WINDOW after the latest, of
    those within LINE_SPAN of the strongest, :func:`position_fits`: a member's step may be
    timed by a broad gain scan samples off, the strongest's too), each with the line's parts
    (those of any member: one bias step moves the same things in all its detectors, and a
    part too weak to pay in one detector is still there); each member takes its fit there
    and keeps its own time where its delta chi^2 there falls more than TIME_LEVEL short of
    its own best. The line's time error: :func:`time_sigma_s` on the summed profile, at least
    TIME_CUSP_SCALE over the members' summed rate. The time is counted once, in the
    strongest member; the others have ``shared_time``. Fewer than two joining: unchanged."""
    events = [event for event, *_ in members]
    times_s = members[0][2].times_s
    # around the members' steps near the strongest; one farther keeps its own time
    samples = [int(np.searchsorted(times_s, e.time_s - 1e-9)) for e in events]
    centre = samples[max(range(len(events)), key=lambda m: events[m].significance)]
    near = [i for i in samples if abs(i - centre) <= LINE_SPAN]
    edge, n = members[0][2].edge, times_s.size
    window = range(max(edge, min(near) - LINE_WINDOW), min(n - edge, max(near) + LINE_WINDOW + 1))
    positions = [i for i in window if all(search.valid[i] for _, _, search, _ in members)]
    if not positions:
        return events
    parts = tuple(part for part in PARTS if any(part in e.parts for e in events))
    fits = [
        position_fits(
            r_f, s.w, s.valid, s.signal_k, positions, s.bank() if bank is None else bank, parts
        )
        for _, r_f, s, bank in members
    ]
    profiles = np.array([[fit[0] for fit in member_fits] for member_fits in fits])
    j = int(np.argmax(profiles.sum(axis=0)))
    own_best = np.array(
        [max(e.significance**2, row.max()) for e, row in zip(events, profiles, strict=True)]
    )
    joining = [m for m in range(len(members)) if profiles[m, j] >= own_best[m] - TIME_LEVEL]
    if len(joining) < 2:
        return events
    retimed = list(events)
    for m in joining:  # each joining member's fit at the line's sample
        fitted = event_of(fits[m][j], float(times_s[positions[j]]), events[m].detector, parts)
        retimed[m] = StepEvent(**{**fitted.__dict__, "sharp": events[m].sharp})
    rate = sum(members[m][2].rate(retimed[m]) for m in joining)
    summed = profiles[joining].sum(axis=0)
    sigma_t = max(time_sigma_s(summed, j, fs), TIME_CUSP_SCALE / max(rate, 1e-300) / fs)
    strongest = max(joining, key=lambda m: retimed[m].significance)
    for m in joining:
        shared = {"sigma_time_s": sigma_t, "shared_time": m != strongest}
        retimed[m] = StepEvent(**{**retimed[m].__dict__, **shared})
    return retimed
