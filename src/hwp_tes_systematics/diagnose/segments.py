"""Recordings longer than memory allows: diagnosed segment by segment, then combined.

A recording whose diagnosis would need more memory than the budget
(:func:`.recording.diagnosis_memory_bytes`, ~1850 B per detector-sample, against the
available memory or ``--memory-gb``) is cut into equal segments that fit it. Each segment
is read from the file alone (:func:`.recording.read_recording` with ``samples``) and
diagnosed in full (:func:`.pipeline.diagnose`; its report in ``segments/<i>/``), so the
peak memory is one segment's. The segments' findings are then combined:

* an effect, with the segments that selected it. A parameter they all fitted is their
  inverse-variance mean, sigma = (sum_i sigma_i^-2)^-1/2, with the consistency
  chi2 = sum_i ((x_i - mean) / sigma_i)^2 on n - 1 dof; p < ``VARIES_P`` marks it as
  varying between segments (the effect changes over the recording, or a segment's fit
  absorbs something else), with ``sigma_scaled`` = sigma sqrt(chi2 / (n - 1)) beside
  sigma (the Particle Data Group's scale factor). Every segment's value stays beside it
  (``per_segment``). The events of an event effect (glitches) are kept per segment,
  their times counted from the start of the recording;
* Delta chi2 and Delta BIC: sums over the segments that selected the effect;
* look-alikes over the recording: two effects selected in different segments, each in
  the other's place (the other detected on its own at the step that added it, or
  replaced), are named as not told apart, with their Delta BIC summed over the segments
  and, where every segment logged it, the sum of the swaps' margins under each segment's
  final noise (:func:`.segment_look_alikes.look_alikes_across_segments`);
* the nominal adjustments per detector, combined as the parameters;
* unexplained structure: every segment's, with the segment and its start;
* chi2, BIC, N_eff and dof: sums over the segments.

What this does not do, and the report says: an effect below one segment's detection
threshold is not found although the whole recording might show it; a drift spanning
the recording is fitted in each segment as its own drift (its shape coefficients then
differ between segments, which the consistency chi2 shows).
"""

from __future__ import annotations

import gc
import logging
import math
import time
from pathlib import Path

import numpy as np
from scipy import stats

from ..io import atomic_path
from .bound.requirement_check import (
    NONLINEARITY_FAMILY,
    bound_nonlinearity,
    compare_nonlinearity,
    load_requirement,
)
from .effects import CATALOG, family_of
from .effects.event_groups import coincidence_groups
from .model import load_sky
from .pipeline import diagnose
from .recording import read_recording
from .recording_checks import (
    DIAGNOSIS_BASE_BYTES,
    DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE,
    RecordingError,
    available_memory_bytes,
    diagnosis_memory_bytes,
    recording_size,
)
from .report.diagnosis import Diagnosis, markdown_report
from .segment_look_alikes import look_alikes_across_segments, name_look_alikes

log = logging.getLogger(__name__)
VARIES_P = 1e-3  # a parameter whose segments disagree at p below this is marked as varying
MIN_SEGMENT_H = 1.0  # h; shorter segments would lose the slow signatures (spin, drifts); assumption

__all__ = [
    "combine_segments",
    "diagnose_segments",
    "look_alikes_across_segments",
    "needs_segments",
    "plan_segments",
]


def needs_segments(n_detectors: int, n_samples: int, memory_budget_bytes=None) -> bool:
    """Whether diagnosing a recording of this size (:func:`.recording.recording_size`) at
    once would exceed the budget (default: the available memory)."""
    budget = available_memory_bytes() if memory_budget_bytes is None else memory_budget_bytes
    return diagnosis_memory_bytes(n_detectors, n_samples) > budget


def plan_segments(
    n_samples: int,
    n_detectors: int,
    sampling_rate_hz: float,
    memory_budget_bytes: float,
    segment_hours: float | None = None,
    source: str = "<recording>",
) -> list[tuple[int, int]]:
    """[(start, stop)] sample ranges of equal length covering the recording: each
    ``segment_hours`` long at most (default: the longest that fits the budget), and never
    more than the budget allows; a budget that allows less than ``MIN_SEGMENT_H`` is an
    error."""
    per_sample = DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE * n_detectors
    fitting = int((memory_budget_bytes - DIAGNOSIS_BASE_BYTES) // per_sample)
    longest = (
        fitting if segment_hours is None else min(fitting, segment_hours * 3600 * sampling_rate_hz)
    )
    shortest = MIN_SEGMENT_H * 3600 * sampling_rate_hz
    if fitting < min(shortest, n_samples):  # the budget's segments: too short to diagnose
        raise RecordingError(
            f"{source}: a memory budget of {memory_budget_bytes / 2**30:.3g} GiB allows "
            f"segments of {max(fitting, 0) / sampling_rate_hz / 3600:.3g} h of {n_detectors} "
            f"detector(s) (~{DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE} B per detector-sample + "
            f"{DIAGNOSIS_BASE_BYTES / 1e9:g} GB), less than the {MIN_SEGMENT_H:g} h a segment "
            "needs; give more memory (--memory-gb) or fewer detectors per file"
        )
    count = max(1, math.ceil(n_samples / longest))
    edges = np.linspace(0, n_samples, count + 1).round().astype(int)
    return list(zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True))


def diagnose_segments(
    path,
    sky_iqu,
    a2_k,
    out_dir=None,
    segment_hours: float | None = None,
    memory_budget_bytes: float | None = None,
    requirement=None,
    **options,
) -> Diagnosis:
    """Diagnose the recording file ``path`` segment by segment (module docstring) and
    return the combined :class:`.report.diagnosis.Diagnosis`; with ``out_dir``, each segment's
    report in ``out_dir/segments/<i>/`` and the combined diagnosis.json and diagnosis.md
    in ``out_dir``. ``options``: passed to :func:`.pipeline.diagnose`."""
    path = [Path(p) for p in path] if isinstance(path, (list, tuple)) else Path(path)
    n_det, n, rate = recording_size(path)
    budget = available_memory_bytes() if memory_budget_bytes is None else memory_budget_bytes
    bounds = plan_segments(n, n_det, rate, budget, segment_hours, str(path))
    requirement_given = load_requirement(requirement) if requirement is not None else None
    sky, _ = load_sky(sky_iqu)
    results = []
    began = time.monotonic()
    for index, (start, stop) in enumerate(bounds):
        elapsed = time.monotonic() - began
        log.info(
            "%s: segment %d of %d, %.2f-%.2f h%s",
            path,
            index + 1,
            len(bounds),
            start / rate / 3600,
            stop / rate / 3600,
            # the segments are of equal length: the ones done give the time left
            f" (elapsed {elapsed / 60:.1f} min, ~{elapsed / index * (len(bounds) - index) / 60:.1f} "
            "min left)"
            if index
            else "",
        )
        recording = read_recording(path, budget, samples=(start, stop))
        segment_dir = None if out_dir is None else Path(out_dir) / "segments" / str(index)
        result = diagnose(
            recording, sky, a2_k, out_dir=segment_dir, requirement=requirement, **options
        )
        results.append(result.to_dict())
        del recording, result
        gc.collect()
    combined = combine_segments(results, bounds, rate, requirement_given or load_requirement())
    combined["recording"]["sky"] = str(sky_iqu) if isinstance(sky_iqu, (str, Path)) else "array"
    diagnosis = Diagnosis(combined)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(out_dir / "diagnosis.json") as temporary:
            temporary.write_text(diagnosis.to_json())
        with atomic_path(out_dir / "diagnosis.md") as temporary:
            temporary.write_text(segments_markdown(combined))
    return diagnosis


def _combined_value(entries: list[dict]) -> dict:
    """One parameter over segments: inverse-variance mean, its sigma, the consistency."""
    values = np.array([e["value"] for e in entries], dtype=float)
    sigmas = np.array([np.nan if e["sigma"] is None else e["sigma"] for e in entries], dtype=float)
    out = {key: entries[0][key] for key in entries[0] if key not in ("value", "sigma")}
    if np.all(np.isfinite(sigmas) & (sigmas > 0)):
        weights = sigmas**-2.0
        mean = float(np.sum(weights * values) / np.sum(weights))
        chi2 = float(np.sum(((values - mean) / sigmas) ** 2))
        dof = len(values) - 1
        p_value = float(stats.chi2.sf(chi2, dof)) if dof else 1.0
        out.update(value=mean, sigma=float(np.sum(weights) ** -0.5))
        out.update(consistency_chi2=chi2, consistency_dof=dof, consistency_p=p_value)
        out["varies_between_segments"] = bool(dof and p_value < VARIES_P)
        if out["varies_between_segments"]:  # the PDG's scale factor sqrt(chi2 / dof)
            out["sigma_scaled"] = out["sigma"] * math.sqrt(chi2 / dof)
    else:
        out.update(value=float(np.mean(values)), sigma=None)
    return out


def _event_parameters(found: list[tuple[int, dict]], starts_s: list[float]) -> dict:
    """An event effect's parameters, per segment, times from the recording's start."""
    out = {}
    for index, effect in found:
        for name, entry in effect["parameters"].items():
            entry = dict(entry, segment=index)
            if entry["unit"] == "s" and entry["parameter"] == "time":
                entry["value"] = entry["value"] + starts_s[index]
            out[f"segment{index}.{name}"] = entry
    return out


def _from_recording_start(scope: dict, start_s: float) -> dict:
    """A segment's ``scope`` with its events' times (a coincidence scope's) counted from
    the recording's start, as the combined report's event parameters are."""
    if "times_s" not in scope:
        return scope
    times_s = [t + start_s for t in scope["times_s"]]
    groups = coincidence_groups(times_s, scope["groups"].values())
    return {**scope, "groups": groups, "times_s": times_s}


def _combined_scope(found: list[tuple[int, dict]], starts_s) -> dict:
    """The segments' scopes (and a family's ``members``) of an effect: ``scope`` where every
    segment that selected it gives the same, else ``scope_per_segment`` {segment: scope},
    event times from the recording's start."""
    out = {}
    members = sorted({m for _, effect in found for m in effect.get("members", [])})
    if members:
        out["members"] = members
    scopes = {
        index: _from_recording_start(effect["scope"], starts_s[index])
        for index, effect in found
        if "scope" in effect
    }
    if not scopes:
        return out
    if len(scopes) == len(found) and all(s == scopes[found[0][0]] for s in scopes.values()):
        return out | {"scope": scopes[found[0][0]]}
    return out | {"scope_per_segment": scopes}


def _combined_effect(name: str, found: list[tuple[int, dict]], starts_s, n_segments) -> dict:
    best_index, best = max(found, key=lambda item: item[1]["delta_chi2"])
    indices = [index for index, _ in found]
    if getattr(CATALOG.get(name), "events", False):
        parameters = _event_parameters(found, starts_s)
    else:
        shared = set.intersection(*(set(effect["parameters"]) for _, effect in found))
        parameters = {}
        for parameter in best["parameters"]:
            entries = [effect["parameters"][parameter] for _, effect in found]
            if parameter in shared:
                combined = _combined_value(entries)
                combined["per_segment"] = [
                    {"segment": index, "value": e["value"], "sigma": e["sigma"]}
                    for index, e in zip(indices, entries, strict=True)
                ]
                parameters[parameter] = combined
    varying = [p for p, entry in parameters.items() if entry.get("varies_between_segments")]
    where = f"selected in segment(s) {', '.join(map(str, indices))} of {n_segments}"
    evidence = f"{where}; in segment {best_index}: {best['evidence']}"
    if varying:
        evidence += (
            f"; {', '.join(varying)} differ between segments beyond their errors "
            f"(p < {VARIES_P:g}): the effect changes over the recording, or a segment's fit "
            "absorbs something else (their errors scaled by the segments' scatter, "
            "sqrt(chi2 / dof): sigma_scaled in diagnosis.json)"
        )
    return {
        **{key: best[key] for key in ("name", "title", "signature", "main_parameters")},
        **_combined_scope(found, starts_s),
        "parameters": parameters,
        "delta_chi2": float(sum(effect["delta_chi2"] for _, effect in found)),
        "delta_bic": float(sum(effect["delta_bic"] for _, effect in found)),
        "evidence": evidence,
        "look_alikes": sorted({a for _, effect in found for a in effect.get("look_alikes", [])}),
        "segments": indices,
        "partial": any(effect.get("partial", False) for _, effect in found),
        "varies_between_segments": varying,
    }


def combine_segments(
    results: list[dict], bounds: list[tuple[int, int]], sampling_rate_hz: float, requirement
) -> dict:
    """The recording's diagnosis from its segments' (``results``, diagnosis.json-shaped,
    in order; ``bounds`` their sample ranges): module docstring. ``requirement``: the
    loaded requirement a found nonlinearity is compared with."""
    starts_s = [start / sampling_rate_hz for start, _ in bounds]
    n_segments = len(results)
    by_name: dict[str, list[tuple[int, dict]]] = {}
    for index, result in enumerate(results):
        for effect in result["effects"]:
            by_name.setdefault(effect["name"], []).append((index, effect))
    effects = [_combined_effect(n, found, starts_s, n_segments) for n, found in by_name.items()]
    effects.sort(key=lambda effect: -effect["delta_chi2"])
    threshold = results[0]["delta_bic_threshold"]
    name_look_alikes(effects, look_alikes_across_segments(results, threshold), threshold)
    unexplained = []
    for index, result in enumerate(results):
        for entry in result["unexplained"]:
            hours = starts_s[index] / 3600
            text = f"segment {index} (from {hours:.3g} h): {entry['text']}"
            unexplained.append(
                {**entry, "segment": index, "segment_start_s": starts_s[index], "text": text}
            )
    adjustments = {}
    for detector in results[0]["nominal_adjustments"]:
        adjustments[detector] = {}
        for quantity, item in results[0]["nominal_adjustments"][detector].items():
            entries = [r["nominal_adjustments"][detector][quantity] for r in results]
            adjustments[detector][quantity] = {
                **_combined_value(entries),
                "nominal": item["nominal"],
            }
    nonlinearity = next((e for e in effects if family_of(e["name"]) == NONLINEARITY_FAMILY), None)
    requirement_check = None
    beside = [r.get("requirement_check") or {} for r in results]  # each segment's bound
    if nonlinearity is not None:
        requirement_check = {
            "effect": nonlinearity["name"],
            **compare_nonlinearity(nonlinearity, requirement),
        }
    elif all("parameters" in check and check["effect"] is None for check in beside):
        parameters = {
            key: _combined_value([check["parameters"][key] for check in beside])
            for key in beside[0]["parameters"]
        }
        delta_chi2 = float(sum(check["delta_chi2"] for check in beside))
        requirement_check = {
            "effect": None,
            **bound_nonlinearity(parameters, requirement, delta_chi2),
        }
    ambiguous = [  # segments whose fit had a second solution (bound.step._second_solutions)
        index
        for index, check in enumerate(beside)
        if any("second_solution" in d for d in check.get("detectors", []))
    ]
    if requirement_check is not None and ambiguous:
        requirement_check["segments_with_a_second_solution"] = ambiguous
        requirement_check["sentence"] += (
            f" Segments {', '.join(map(str, ambiguous))} have a second solution each (their "
            "own checks): the combined g1 holds only one of them."
        )
    total = {key: float(sum(r[key] for r in results)) for key in ("chi2_before", "chi2_after")}
    total.update({key: float(sum(r[key] for r in results)) for key in ("bic_before", "bic_after")})
    first = results[0]
    recording = dict(first["recording"])
    durations = [r["recording"]["duration_s"] for r in results]
    recording["duration_s"] = float(sum(durations))
    recording["flagged_fraction"] = float(
        np.average([r["recording"]["flagged_fraction"] for r in results], weights=durations)
    )
    steps = [
        {**step, "note": f"segment {index}: {step['note']}"}
        for index, result in enumerate(results)
        for step in result["steps"]
    ]
    lines = [
        {**line, "identification": f"[segment {index}] {line['identification']}"}
        for index, result in enumerate(results)
        for line in result["lines"]
    ]

    def median_noise(which: str) -> list[dict]:
        """The segments' median of each number of ``noise[which]``, per detector."""
        return [
            {
                key: float(np.median([r["noise"][which][k][key] for r in results]))
                for key, value in first["noise"][which][k].items()
                if isinstance(value, (int, float))
            }
            for k in range(len(first["noise"][which]))
        ]

    noise = {"nominal": first["noise"]["nominal"], "estimated": median_noise("estimated")}
    if all("final" in r["noise"] for r in results):
        noise["final"] = median_noise("final")
    return {
        "mismatch_found": any(r["mismatch_found"] for r in results),
        "effects": effects,
        "unexplained": unexplained,
        "nominal_adjustments": adjustments,
        **total,
        "dof": int(sum(r["dof"] for r in results)),
        "n_eff": int(sum(r["n_eff"] for r in results)),
        "delta_bic_threshold": first["delta_bic_threshold"],
        "information_criterion": first["information_criterion"] + ", summed over the segments",
        "requirement_check": requirement_check,
        "steps": steps,
        "lines": lines,
        "noise": noise,
        "recording": recording,
        "segments": [
            {
                "segment": index,
                "start_s": starts_s[index],
                "duration_s": durations[index],
                "mismatch_found": result["mismatch_found"],
                "effects": [effect["name"] for effect in result["effects"]],
                "unexplained": len(result["unexplained"]),
                "chi2_after": result["chi2_after"],
                "dof": result["dof"],
                "report": f"segments/{index}/diagnosis.md",
            }
            for index, result in enumerate(results)
        ],
    }


def segments_markdown(combined: dict) -> str:
    """diagnosis.md of a segmented diagnosis: the combined report, then the segments."""
    segments = combined["segments"]
    hours = segments[0]["duration_s"] / 3600
    out = [
        markdown_report(combined).rstrip(),
        "",
        "## Segments",
        "",
        (
            f"The recording was diagnosed in {len(segments)} segments of {hours:.3g} h (its "
            "diagnosis at once would not fit the memory budget); the effects above combine "
            "the segments that selected them (parameters: inverse-variance means, with the "
            "chi2 of the segments about them). An effect below one segment's detection "
            "threshold is not found, and a drift over the whole recording is fitted in each "
            "segment as its own."
        ),
        "",
        "| segment | from [h] | effects | unexplained | chi2 after / dof | report |",
        "|---|---|---|---|---|---|",
    ]
    for s in segments:
        out.append(
            f"| {s['segment']} | {s['start_s'] / 3600:.3g} | {', '.join(s['effects']) or '-'} | "
            f"{s['unexplained']} | {s['chi2_after']:.1f} / {s['dof']} | [{s['report']}]({s['report']}) |"
        )
    return "\n".join(out) + "\n"
