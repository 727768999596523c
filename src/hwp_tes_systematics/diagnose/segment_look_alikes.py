"""Look-alikes over a recording diagnosed in segments (:mod:`.segments`): two effects
selected in different segments, each the other's alternative where it was added, named as
not told apart, with the margins that say which the recording as a whole leans to.
"""

from __future__ import annotations

import itertools
import math

from .effects import family_of, prior_penalty_of


def _family_candidates(step: dict) -> dict[str, float]:
    """{family: its best member's Delta BIC, prior penalty left out} of one step's
    candidates (a segment's diagnosis.json ``steps``)."""
    out: dict[str, float] = {}
    for name, candidate in step.get("candidates", {}).items():
        value = candidate["delta_bic"] - prior_penalty_of(name)
        out[family_of(name)] = min(out.get(family_of(name), math.inf), value)
    return out


def _in_place_of(result: dict, family: str, other: str, threshold: float) -> float | None:
    """In one segment: the Delta BIC by which ``family`` beat ``other`` (< 0) at the step
    that added it, when ``other`` was an alternative there (a candidate detected on its
    own, Delta BIC < ``threshold``, or the effect it replaced); None when it was not."""
    for step in result.get("steps", []):
        added = step.get("added")
        if not added or family_of(added) != family:
            continue
        if step.get("removed") and family_of(step["removed"]) == other:
            return float(step["delta_bic"])  # a swap: its gain
        candidates = _family_candidates(step)
        if candidates.get(other, math.inf) < threshold and family in candidates:
            return float(candidates[family] - candidates[other])
    return None


def _final_margin(result: dict, family: str, other: str) -> float | None:
    """In one segment: minus the BIC margin by which its selected member of ``family`` beat
    the best member of ``other`` put in its place, under the segment's final noise weights
    (diagnosis.json ``swap_margins``; < 0 as :func:`_in_place_of`'s gains); None when the
    segment did not log one (a nonlinear effect, or a report without margins)."""
    margins = (result.get("swap_margins") or {}).get("effects", {})
    values = [
        value
        for name, row in margins.items()
        if family_of(name) == family
        for alternative, value in row.items()
        if family_of(alternative) == other
    ]
    return -min(values) if values else None


def look_alikes_across_segments(results: list[dict], threshold: float) -> list[dict]:
    """Pairs of effects the segments do not tell apart: A selected in some segments
    without B, B in others without A, and in a segment of each the other an alternative
    at the step that added it (:func:`_in_place_of`: detected on its own, or replaced).
    Per pair, those Delta BIC per segment and their sum (A's gains counted negative, B's
    positive: < 0 the recording as a whole leans to A). Those margins are of two kinds (a
    candidate's Delta BIC at the step that added the effect, or a swap's gain after the
    noise refit); where every segment of the pair logged its final margin (the swap's BIC
    under its final noise, :func:`_final_margin`), their sum is given beside it
    (``preference_final_delta_bic``), one kind throughout, and the verdict reads it.
    Effects of disjoint segments that were no alternative to each other (events in
    different hours) are not paired."""
    families = [{family_of(e["name"]): e["name"] for e in r["effects"]} for r in results]
    names = {f: n for found in families for f, n in found.items()}
    pairs = []
    for a, b in itertools.combinations(sorted(names), 2):
        only_a = [i for i, found in enumerate(families) if a in found and b not in found]
        only_b = [i for i, found in enumerate(families) if b in found and a not in found]
        gains_a = {i: _in_place_of(results[i], a, b, threshold) for i in only_a}
        gains_b = {i: _in_place_of(results[i], b, a, threshold) for i in only_b}
        gains_a = {i: g for i, g in gains_a.items() if g is not None}
        gains_b = {i: g for i, g in gains_b.items() if g is not None}
        if not (gains_a and gains_b):
            continue
        pair = {
            "effects": [names[a], names[b]],
            "segments": [only_a, only_b],
            "delta_bic_per_segment": [gains_a, gains_b],
            "preference_delta_bic": float(sum(gains_a.values()) - sum(gains_b.values())),
        }
        final_a = {i: _final_margin(results[i], a, b) for i in gains_a}
        final_b = {i: _final_margin(results[i], b, a) for i in gains_b}
        if None not in (*final_a.values(), *final_b.values()):
            pair["final_delta_bic_per_segment"] = [final_a, final_b]
            pair["preference_final_delta_bic"] = float(
                sum(final_a.values()) - sum(final_b.values())
            )
        pairs.append(pair)
    return pairs


def name_look_alikes(effects: list[dict], pairs: list[dict], threshold: float) -> None:
    """Each pair of :func:`look_alikes_across_segments` named in both effects' entries
    (``look_alikes``, ``look_alikes_across_segments``, a sentence of evidence)."""
    by_name = {effect["name"]: effect for effect in effects}
    for pair in pairs:
        final = "preference_final_delta_bic" in pair
        preference = pair["preference_final_delta_bic" if final else "preference_delta_bic"]
        margins = (
            "each segment's swap under its final noise"
            if final
            else "margins at the steps that added them"
        )
        for side in (0, 1):
            effect, other = by_name[pair["effects"][side]], pair["effects"][1 - side]
            mine, theirs = pair["segments"][side], pair["segments"][1 - side]
            lean = preference if side == 0 else -preference
            if abs(lean) < -threshold:
                verdict = "the recording as a whole does not choose"
            else:
                favoured = "it" if lean < 0 else other
                verdict = f"summed over the segments, the data lean to {favoured}"
            effect["look_alikes"] = sorted(set(effect["look_alikes"]) | {other})
            effect.setdefault("look_alikes_across_segments", []).append(pair)
            effect["evidence"] += (
                f"; NOT told apart from {other} over the recording: selected in segment(s) "
                f"{', '.join(map(str, mine))}, {other} in {', '.join(map(str, theirs))} in "
                f"its place, each the other's alternative where it was added ({verdict}: "
                f"Delta BIC {lean:+.1f}, {margins}); read it as one of the two"
            )
