"""Benchmark of the diagnosis: speed on one recording, and rates on many.

    python benchmarks/diagnose_benchmark.py --hours 24 --nside 64 --effect tes_nonlinearity
    python benchmarks/diagnose_benchmark.py --rates --hours 6 --seeds 5 --clean 20

Speed: simulates the recording (sky + dipole + HWPSS + noise, optionally one injected
effect) with litebird_sim, writes it to HDF5 and reads it back (not timed), then times
``diagnose`` (nominal model and adjustments, residual, noise, locate, stepwise fit,
unexplained) without and with the figures/report. Prints the wall time, the
detector-samples per second and the peak resident memory. Target: a one-day recording at
31 Hz in at most 60 s on 2 cores (``--workers 2``).

Rates (``--rates``): recordings of a pair (``--channel``, default M1-140), each with RANDOM
nominal errors (their spreads times ``--error-scale``, default 1)
(hwp_tes_systematics.diagnose.testbed.nominal_errors: A_2 ~3 %, 2f phase ~1 deg, gain ~1 %,
polarisation angle ~0.5 deg, offsets, noise level ~10 %, knee ~30 %, the supplied sky
rescaled ~5 % plus a residual map) and its own noise seed: ``--clean`` clean ones (false
alarms: ``mismatch_found``), each catalog effect at three amplitudes from barely
detectable to strong (``--seeds`` recordings each; the phases of lines, the sign and
shape of drifts and the times of events drawn per recording), a time constant alone (a 2f
phase adjustment: no effect and its lag in the adjusted phase, or, where the lag of the
other frequencies shows, the effect with its tau), pairs of effects (each at its
amplitudes times PAIR_SCALES: the pair's threshold) and two effects outside the catalog; ``--only`` runs some of these cases (several runs with
far-apart ``--first-seed`` add up). Prints per case the detection rate, the rate at which the
top-ranked effect is the injected one and its main parameter within 3 sigma, the
detection threshold of each effect (the smallest amplitude found in >= 90 % of its
recordings), the false-alarm rate and whether every out-of-catalog effect landed in
``unexplained``. Targets: top-ranked correct >= 90 %, parameter within 3 sigma >= 80 %,
false alarms <= 5 %, every out-of-catalog effect in ``unexplained``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose import (
    diagnose,
    read_recording,
    simulate_recording,
    write_recording,
)
from hwp_tes_systematics.diagnose.effects import family_of
from hwp_tes_systematics.io import reuse_freed_memory, use_base_pages

EFFECTS = {
    "none": [],
    "tes_nonlinearity": [("tes_nonlinearity", {"g1": -0.04})],
    "detector_time_constant": [("detector_time_constant", {"tau": 3e-3})],
    "glitches": [("glitches", {"events": [(0, 3600.0 * h + 100.0, 3e-3, 0.1) for h in range(20)]})],
    "noise_mismatch": [("noise_mismatch", {"net_ukrts": 60.0, "fknee_mhz": 50.0})],
}


# effect -> (main parameter, amplitudes from barely detectable to strong,
#            params(amplitude, rng), accepted top-ranked names). What is not the amplitude is
#            drawn per recording (phases of lines, sign and shape of drifts, times of events):
#            the diagnosis is scored on the effect's physics, not on one configuration of it.


def _phase(rng) -> float:
    return float(rng.uniform(0.0, 2.0 * np.pi))


def _line(n: int, amplitude: float, rng) -> dict:
    """c_n cos + s_n sin of amplitude ``amplitude`` and random phase."""
    phase = _phase(rng)
    return {f"c{n}": amplitude * np.cos(phase), f"s{n}": amplitude * np.sin(phase)}


def _drift(amplitude: float, rng) -> dict:
    """c1 = +-amplitude, c2 and c3 up to half of it: a slow drift of random sign and shape."""
    return {
        "c1": amplitude * rng.choice([-1.0, 1.0]),
        "c2": amplitude * rng.uniform(-0.5, 0.5),
        "c3": amplitude * rng.uniform(-0.5, 0.5),
    }


def _gain_drift(amplitude: float, rng, per_detector: bool) -> dict:
    """g_j of a drift of random sign and shape; ``per_detector``: each detector's drift
    times its own factor in [0.5, 1.5] (each TES its own responsivity, as litebird_sim's
    gain drift draws a slope per detector), else the same in both (a common mode)."""
    factors = rng.uniform(0.5, 1.5, 2) if per_detector else np.ones(2)
    return {f"g{j}": v * factors for j, v in enumerate(_drift(amplitude, rng).values(), 1)}


# gain_drift_common_mode is injected as gain_drift (the same drift in both detectors)
INJECTED_AS = {"gain_drift_common_mode": "gain_drift"}

AMPLITUDES = {
    "tes_nonlinearity": ("g1", [-1e-3, -3e-3, -1e-2], lambda a, rng: {"g1": a}, None),
    "hwpss_harmonics": (
        "c4",
        [2e-6, 6e-6, 20e-6],
        lambda a, rng: {**_line(4, a, rng), **_line(3, a, rng)},
        None,
    ),
    "hwpss_intensity_coupling": (
        "a2c",
        [5e-4, 2e-3, 1e-2],
        lambda a, rng: {"a2c": a * np.cos(p := _phase(rng)), "a2s": a * np.sin(p)},
        None,
    ),
    "hwp_intensity_leakage_4f": (
        "b4c",
        [1e-3, 3e-3, 1e-2],
        lambda a, rng: {"b4c": a * np.cos(p := _phase(rng)), "b4s": a * np.sin(p)},
        None,
    ),
    "gain_drift": ("g1", [1e-3, 3e-3, 3e-2], lambda a, rng: _gain_drift(a, rng, True), None),
    "gain_drift_common_mode": (
        "g1",
        [1e-3, 3e-3, 3e-2],
        lambda a, rng: _gain_drift(a, rng, False),
        {"gain_drift"},
    ),
    "hwp_temperature_drift": (
        "c1",  # [K]; checked as r1 = c1 / A_2, the relative drift shared by the detectors
        [3e-6, 1e-5, 1e-4],
        _drift,
        {"hwp_temperature_drift", "hwpss_slow_modulation"},
    ),
    "glitches": (
        None,
        [3e-4, 1e-3, 3e-3],
        lambda a, rng: {
            "events": [
                (k % 2, 600.0 + 1500.0 * k + rng.uniform(0.0, 1000.0), a, 0.1) for k in range(4)
            ]
        },
        None,
    ),
    "hwpss_sine_modulation": (
        None,
        [1e-4, 1e-3, 1e-2],
        lambda a, rng: {
            "relative": a,
            "period_s": float(rng.uniform(3600.0, 3 * 3600.0)),
            "phase_rad": _phase(rng),
        },
        {"hwpss_slow_modulation", "hwp_temperature_drift"},
    ),
}
# pair -> (injected effects, the effects the report must list). A time constant is a 2f
# phase adjustment, not an effect: for 2 pi f tau << 1 a single pole is a time delay, the
# nonlinearity's 4f line lags by twice the 2f lag, as d_nom^2 with the adjusted phase does.
PAIRS = {
    "nonlinearity+gain_drift": (
        [("tes_nonlinearity", {"g1": -1e-2}), ("gain_drift", {"g1": [1e-2, 0.6e-2]})],
        {"tes_nonlinearity", "gain_drift"},
    ),
    "nonlinearity+4f_hwpss": (
        [("tes_nonlinearity", {"g1": -2e-2}), ("hwpss_harmonics", {"c4": 60e-6, "s4": -30e-6})],
        {"tes_nonlinearity", "hwpss_harmonics"},
    ),
    "nonlinearity+time_constant": (
        [("tes_nonlinearity", {"g1": -2e-2}), ("detector_time_constant", {"tau": 3e-3})],
        {"tes_nonlinearity"},
    ),
    "harmonics+glitches": (
        [
            ("hwpss_harmonics", {"c3": 20e-6}),
            ("glitches", {"events": [(0, 900.0, 3e-3, 0.1), (1, 2000.0, 5e-3, 0.05)]}),
        ],
        {"hwpss_harmonics", "glitches"},
    ),
}
# Each pair also runs with its members' amplitudes (PAIR_AMPLITUDES) scaled by these factors:
# from about the weaker member's single-effect threshold in 6 h (g1 1e-3, the 4f and 3f
# lines 6e-6 K, a gain drift 1e-3; glitches 3e-4 K, below their 3e-3 K threshold) to the
# pair as defined (x1). The pair's threshold: the smallest factor at which both members are
# reported, or the weaker one named as a look-alike, in >= 90 % of the recordings.
PAIR_SCALES = (0.1, 0.3, 1.0)
PAIR_AMPLITUDES = {  # effect -> its parameters that the scale multiplies
    "tes_nonlinearity": ("g1",),
    "gain_drift": ("g1",),
    "hwpss_harmonics": ("c3", "c4", "s4"),
    "glitches": ("events",),  # each event's amplitude
    "detector_time_constant": (),  # a 2f phase adjustment: not scaled
}


def scaled_pair(effects: list, scale: float) -> list:
    """A pair's effects with their amplitudes (PAIR_AMPLITUDES) times ``scale``."""
    out = []
    for name, params in effects:
        params = dict(params)
        for key in PAIR_AMPLITUDES[name]:
            if key == "events":
                params[key] = [(k, t, a * scale, tau) for k, t, a, tau in params[key]]
            elif key in params:
                params[key] = (np.asarray(params[key]) * scale).tolist()
        out.append((name, params))
    return out


# a time constant alone: its lag atan(2 pi 2 f_HWP tau) in the 2f phase adjustment (no effect),
# or, where the lag of the other frequencies shows, the effect with its tau
TIME_CONSTANTS_S = [1e-3, 3e-3, 1e-2]
OUTSIDE = {
    "pickup_line": ("pickup_line", {"freq_hz": 1.7, "amplitude_k": 20e-6}),
    "spin_modulated_3f": ("hwpss_spin_modulation", {"harmonic": 3, "amplitude_k": 40e-6}),
}


def _one(support, effects, seed, settings, folder, with_errors=False):
    """Simulate with random nominal errors, diagnose; the result (and the errors drawn, with
    ``with_errors``). One line on stderr. ``settings``: hours, channel, error_scale."""
    started = time.perf_counter()
    errors = support.nominal_errors(np.random.default_rng(seed), scale=settings.error_scale)
    recording, _ = support.recorded_with_errors(
        Path(folder),
        effects,
        10_000 + seed,
        errors,
        hours=settings.hours,
        name=f"r{seed}.h5",
        channel=settings.channel,
        a2_k=support.A2_K,  # M1-140's A_2 on any --channel, the diagnosis told the same
    )
    result = diagnose(recording, support.supplied_sky(errors), support.A2_K, figures=False)
    names = [e["name"] for e in result["effects"]] or ["-"]
    injected = ", ".join(name for name, _ in effects) or "clean"
    print(
        f"recording {seed} ({injected}): reported {', '.join(names)}; "
        f"{time.perf_counter() - started:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    return (result, errors) if with_errors else result


def _lag_in_phase(result, errors, tau_s) -> bool:
    """The fitted 2f phase = phase error + 2 x polarisation-angle error + atan(2 pi 2 f_HWP
    tau), within 3 sigma, on every detector."""
    lag_deg = np.degrees(np.arctan(2 * np.pi * 2 * result["recording"]["f_hwp_hz"] * tau_s))
    for k, det in enumerate(result["recording"]["detectors"]):
        phase = result["nominal_adjustments"][det]["hwpss_2f_phase"]
        truth = errors["phase_deg"][k] + 2 * errors["pol_angle_deg"][k] + lag_deg
        if not abs(phase["value"] - truth) < 3 * phase["sigma"] + 1e-6:
            return False
    return True


def _checked(effect: str, param: str, injected: dict, support) -> tuple[str, object]:
    """(parameter, truth) checked for the main parameter: the injected value (one, or one
    per detector); for the HWP temperature drift, r1 = c1 / A_2, the relative drift of the
    HWP emission shared by the detectors."""
    if effect == "hwp_temperature_drift":
        return "r1", injected["c1"] / support.A2_K
    return param, injected[param]


def _within(result, effect, name, truth) -> bool:
    """Main parameter within 3 sigma of its truth on every detector (``truth``: one value
    or one per detector), or of the common value where the effect is shared.

    For g1 the truth is the injected value itself: the recorder applies the gain error to
    the incoming signal, before the TES response, and the adjusted nominal model carries
    the same gain, so the fitted g1 is not rescaled by it.
    """
    for item in result["effects"]:
        if family_of(item["name"]) != effect:
            continue
        detectors = result["recording"]["detectors"]
        keys = [f"{name}[common]"] if f"{name}[common]" in item["parameters"] else None
        truths = np.broadcast_to(np.asarray(truth, dtype=float), (len(detectors),))
        for k, key in enumerate(keys or [f"{name}[{det}]" for det in detectors]):
            entry = item["parameters"].get(key)
            if entry is None:
                return False
            if not abs(entry["value"] - truths[k]) < 3 * entry["sigma"]:
                return False
        return True
    return False


def _tally(counts: dict, key: str, **increments) -> None:
    """Add ``increments`` to the counters ``counts[key]`` (created at zero)."""
    entry = counts.setdefault(key, {})
    for name, value in increments.items():
        entry[name] = entry.get(name, 0) + int(value)


def rates(arguments) -> dict:
    """Many recordings with random nominal errors: the counts behind the rates (module
    docstring), printed as they come and returned (``--out`` writes them as JSON)."""
    from hwp_tes_systematics.diagnose import testbed as support

    hours, n_seeds = arguments.hours, arguments.seeds
    started = time.perf_counter()
    counts = {
        "hours": hours,
        "channel": arguments.channel,
        "error_scale": arguments.error_scale,
        "first_seeds": [arguments.first_seed],
        "clean": {},
        "effects": {},
        "pairs": {},
        "time_constants": {},
        "outside": {},
    }

    def wanted(case: str) -> bool:
        return not arguments.only or case in arguments.only

    with tempfile.TemporaryDirectory() as folder:
        seed = arguments.first_seed
        for _ in range(arguments.clean if wanted("clean") else 0):
            result = _one(support, [], seed, arguments, folder)
            seed += 1
            _tally(counts, "clean", n=1, alarms=result["mismatch_found"])
        for effect, (param, amplitudes, make, accepted) in AMPLITUDES.items():
            if not wanted(effect):
                continue
            accepted = accepted or {effect}
            cases = counts["effects"].setdefault(effect, {"param": param, "amplitudes": {}})
            for amplitude in amplitudes:
                for _ in range(n_seeds):
                    injected = make(amplitude, np.random.default_rng([seed, 1]))
                    injection = [(INJECTED_AS.get(effect, effect), injected)]
                    result = _one(support, injection, seed, arguments, folder)
                    seed += 1
                    names = [family_of(e["name"]) for e in result["effects"]]
                    top_ok = bool(names) and names[0] in accepted
                    ties = {
                        family_of(n) for n in (result["effects"] or [{}])[0].get("look_alikes", [])
                    }
                    _tally(
                        cases["amplitudes"],
                        f"{amplitude:g}",
                        n=1,
                        found=bool(accepted & set(names)),  # among the effects
                        reported=bool(names),
                        correct=top_ok,  # ranked first
                        tied=bool(names) and not top_ok and bool(accepted & ties),
                        within=param is not None
                        and top_ok
                        and _within(result, names[0], *_checked(effect, param, injected, support)),
                    )
                print("  " + _amplitude_line(effect, param, amplitude, cases), flush=True)
        for label, (effects, expected) in PAIRS.items():
            if not wanted(label):
                continue
            ladder = counts.setdefault("pair_ladder", {}).setdefault(label, {})
            for scale in PAIR_SCALES:
                for _ in range(n_seeds):
                    result = _one(support, scaled_pair(effects, scale), seed, arguments, folder)
                    seed += 1
                    names = {family_of(e["name"]) for e in result["effects"]}
                    alike = {family_of(n) for e in result["effects"] for n in e["look_alikes"]}
                    members = {f"found_{m}": m in names for m in expected}
                    found = expected <= names
                    if scale == 1.0:  # the pair as defined
                        _tally(counts["pairs"], label, n=1, found=found)
                    _tally(
                        ladder,
                        f"{scale:g}",
                        n=1,
                        found=found,
                        named=expected <= names | alike,
                        **members,
                    )
                print("  " + _pair_line(label, scale, ladder[f"{scale:g}"]), flush=True)
        if wanted("detector_time_constant"):
            for tau in TIME_CONSTANTS_S:
                for _ in range(n_seeds):
                    result, errors = _one(
                        support,
                        [("detector_time_constant", {"tau": tau})],
                        seed,
                        arguments,
                        folder,
                        with_errors=True,
                    )
                    seed += 1
                    top = (result["effects"] or [{"name": None}])[0]["name"]
                    _tally(
                        counts["time_constants"],
                        f"{tau:g}",
                        n=1,
                        in_phase=not result["mismatch_found"]
                        and _lag_in_phase(result, errors, tau),
                        as_effect=top == "detector_time_constant"
                        and _within(result, "detector_time_constant", "tau", tau),
                    )
        for label, effect in OUTSIDE.items():
            if not wanted(label):
                continue
            for _ in range(n_seeds):
                result = _one(support, [effect], seed, arguments, folder)
                seed += 1
                _tally(counts["outside"], label, n=1, landed=bool(result["unexplained"]))
    counts["recordings"] = seed - arguments.first_seed
    counts["seconds"] = round(time.perf_counter() - started)
    return counts


def _amplitude_line(effect: str, param: str | None, amplitude: float, cases: dict) -> str:
    c = cases["amplitudes"][f"{amplitude:g}"]
    return (
        f"{effect} {param or 'amplitude'} = {amplitude:g}: found {c['found']}/{c['n']}, "
        f"top-ranked correct {c['correct']}/{c['reported']} reported"
        + (f" ({c['tied']} more with the truth named as an equal look-alike)" if c["tied"] else "")
        + (f", parameter within 3 sigma {c['within']}/{c['correct']}" if param else "")
    )


SETTINGS = ("hours", "channel", "error_scale")  # what runs must share to be added up


def merge_counts(a: dict, b: dict) -> dict:
    """Two runs' counts added up (numbers summed, lists joined); ValueError if the runs'
    settings (duration, channel, error scale) differ."""
    out = dict(a)
    for key, value in b.items():
        if key in SETTINGS:
            if a.get(key) != value:
                raise ValueError(f"runs with different {key}: {a.get(key)} and {value}")
        elif key not in a:
            out[key] = value
        elif isinstance(value, dict):
            out[key] = merge_counts(a[key], value)
        elif isinstance(value, (list, int, float)):
            out[key] = a[key] + value
    return out


def _pair_line(label: str, scale: float, c: dict) -> str:
    members = ", ".join(f"{key[6:]} {c[key]}" for key in sorted(c) if key.startswith("found_"))
    return (
        f"pair {label} x{scale:g}: both reported {c['found']}/{c['n']}, both reported or "
        f"the weaker named as a look-alike {c['named']}/{c['n']} (each reported: {members})"
    )


def pair_thresholds(counts: dict) -> dict:
    """{pair: the smallest scale at which both members are reported or named in >= 90 %}."""
    out = {}
    for label, ladder in counts.get("pair_ladder", {}).items():
        good = [float(s) for s, c in ladder.items() if c["named"] >= 0.9 * c["n"]]
        out[label] = min(good) if good else None
    return out


def summary(counts: dict) -> list[str]:
    """The rates, the targets' four numbers and the thresholds, as lines of text."""
    lines = [
        (
            f"{counts['hours']:g} h {counts.get('channel', 'M1-140')} pair recordings with random "
            f"nominal errors (x{counts.get('error_scale', 1.0):g}) "
            f"({counts['recordings']} recordings, {counts['seconds']} s of run time summed over "
            f"{len(counts['first_seeds'])} run(s), first seeds {counts['first_seeds']})"
        )
    ]
    clean = counts["clean"]
    if clean:
        lines.append(f"  clean: false alarms {clean['alarms']} / {clean['n']}")
    top_ok = top_n = tied = par_ok = par_n = 0
    thresholds, thresholds_named = {}, {}
    for effect, cases in counts["effects"].items():
        detected, named = [], []
        for label, c in cases["amplitudes"].items():
            lines.append("  " + _amplitude_line(effect, cases["param"], float(label), cases))
            top_ok, top_n, tied = top_ok + c["correct"], top_n + c["reported"], tied + c["tied"]
            if cases["param"] is not None:
                par_ok, par_n = par_ok + c["within"], par_n + c["correct"]
            if c["found"] >= 0.9 * c["n"]:
                detected.append(float(label))
            if min(c["found"] + c["tied"], c["n"]) >= 0.9 * c["n"]:
                named.append(float(label))
        thresholds[effect] = min(detected, key=abs) if detected else None
        thresholds_named[effect] = min(named, key=abs) if named else None
    for label, c in counts["pairs"].items():
        expected = " and ".join(sorted(PAIRS[label][1])) if label in PAIRS else "both"
        lines.append(f"  pair {label}: {expected} found {c['found']}/{c['n']}")
    for label, ladder in counts.get("pair_ladder", {}).items():
        for scale in sorted(ladder, key=float):
            lines.append("  " + _pair_line(label, float(scale), ladder[scale]))
    for label, scale in pair_thresholds(counts).items():
        amplitudes = "; ".join(
            f"{name} {params}" for name, params in scaled_pair(PAIRS[label][0], scale or 1.0)
        )
        lines.append(
            f"  pair {label}: threshold x{scale:g} ({amplitudes})"
            if scale is not None
            else f"  pair {label}: not reached up to x{max(PAIR_SCALES):g}"
        )
    for tau, c in counts["time_constants"].items():
        lines.append(
            f"  detector_time_constant tau = {tau} s alone: its lag in the 2f phase adjustment "
            f"(no effect) {c['in_phase']}/{c['n']}, reported as the effect with tau within 3 "
            f"sigma {c['as_effect']}/{c['n']}, otherwise {c['n'] - c['in_phase'] - c['as_effect']}"
        )
    for label, c in counts["outside"].items():
        lines.append(f"  outside the catalog {label}: in unexplained {c['landed']}/{c['n']}")
    lines.append(
        f"top-ranked effect correct: {top_ok}/{top_n} = {top_ok / max(top_n, 1):.1%} of the "
        f"recordings where an effect was reported (target >= 90 %); {tied} more had the truth "
        "named as an equal look-alike of the top one"
    )
    lines.append(
        f"main parameter within 3 sigma: {par_ok}/{par_n} = {par_ok / max(par_n, 1):.1%} "
        "(target >= 80 %)"
    )
    if clean:
        lines.append(
            f"false alarms: {clean['alarms']}/{clean['n']} = "
            f"{clean['alarms'] / max(clean['n'], 1):.1%} (target <= 5 %)"
        )
    outside_ok = all(c["landed"] == c["n"] for c in counts["outside"].values())
    lines.append(f"every out-of-catalog effect in unexplained: {outside_ok}")
    lines.append(
        "detection thresholds (smallest amplitude found >= 90 %; in brackets where it differs: "
        "found or named as the equal look-alike of the effect reported instead):"
    )
    for effect, value in thresholds.items():
        text = f"{value:g}" if value is not None else "above the largest tried"
        if thresholds_named[effect] != value and thresholds_named[effect] is not None:
            text += f" ({thresholds_named[effect]:g})"
        lines.append(f"  {effect}: {text}")
    return lines


def rates_figure(counts: dict, path: Path) -> None:
    """Per effect, versus amplitude: found, top-ranked correct and parameter within 3 sigma
    (fractions of the recordings); the last panel: false alarms, pairs, time constants and
    out-of-catalog effects."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hwp_tes_systematics.io import atomic_path

    effects = list(counts["effects"].items())
    columns = 4
    rows = (len(effects) + 1 + columns - 1) // columns
    figure, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3.2 * rows), squeeze=False)
    axes = axes.ravel()
    for ax, (effect, cases) in zip(axes, effects, strict=False):
        amplitudes = [float(a) for a in cases["amplitudes"]]
        entries = list(cases["amplitudes"].values())
        x = np.abs(amplitudes)
        n = np.array([c["n"] for c in entries], dtype=float)
        named = [min(c["found"] + c["tied"], c["n"]) for c in entries] / n
        ax.plot(x, named, "o-", color="0.7", lw=3, label="found or named as equal look-alike")
        ax.plot(x, [c["found"] for c in entries] / n, "o-", label="found")
        ax.plot(x, [c["correct"] for c in entries] / n, "s--", label="ranked first")
        if cases["param"] is not None:
            ax.plot(x, [c["within"] for c in entries] / n, "^:", label="ranked first, param. 3σ")
        ax.axhline(0.9, color="0.6", lw=0.8)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_ylim(-0.05, 1.05)
        ax.set_title(effect, fontsize=10)
        ax.set_xlabel(f"|{cases['param'] or 'amplitude'}| (n = {int(n.max())} each)")
    axes[0].set_ylabel("fraction of recordings")
    axes[0].legend(fontsize=7, loc="lower right")
    ax = axes[len(effects)]
    bars = []
    if counts["clean"]:
        c = counts["clean"]
        bars.append(("clean: no alarm", 1 - c["alarms"] / c["n"], c["n"]))
    bars += [(f"pair {k}", c["found"] / c["n"], c["n"]) for k, c in counts["pairs"].items()]
    bars += [
        (f"tau {k} s: in 2f phase or as tau", (c["in_phase"] + c["as_effect"]) / c["n"], c["n"])
        for k, c in counts["time_constants"].items()
    ]
    bars += [
        (f"{k}: unexplained", c["landed"] / c["n"], c["n"]) for k, c in counts["outside"].items()
    ]
    ax.barh([f"{label} ({n})" for label, _, n in bars], [v for _, v, _ in bars], color="C2")
    ax.set_xlim(0, 1.05)
    ax.tick_params(axis="y", labelsize=7)
    ax.set_title("the other cases", fontsize=10)
    for extra in axes[len(effects) + 1 :]:
        extra.axis("off")
    figure.suptitle(
        f"diagnosis of {counts['recordings']} {counts['hours']:g}-hour "
        f"{counts.get('channel', 'M1-140')} pair recordings with random nominal errors "
        f"(x{counts.get('error_scale', 1.0):g})"
    )
    figure.tight_layout()
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)


def run_rates(arguments) -> None:
    """--rates (a run, optionally written with --out) or --combine (runs added up); the
    summary printed, the figure written with --figure."""
    if arguments.combine:
        counts = None
        for path in arguments.combine:
            try:
                loaded = json.loads(Path(path).read_text())
            except (OSError, json.JSONDecodeError) as error:
                sys.exit(f"{path}: not a rates file written by --rates --out ({error})")
            try:
                counts = loaded if counts is None else merge_counts(counts, loaded)
            except ValueError as error:
                sys.exit(f"{path}: cannot be added to the runs before it: {error}")
    else:
        counts = rates(arguments)
    if arguments.out:
        from hwp_tes_systematics.io import atomic_path

        with atomic_path(arguments.out) as temporary:
            Path(temporary).write_text(json.dumps(counts, indent=1))
    print("\n".join(summary(counts)))
    if arguments.figure:
        rates_figure(counts, Path(arguments.figure))
        print(f"figure: {arguments.figure}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--hours", type=float, default=24.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--a2-k", type=float, default=0.264)
    parser.add_argument("--effect", choices=sorted(EFFECTS), default="tes_nonlinearity")
    parser.add_argument("--workers", type=int, default=2, help="FFT threads")
    parser.add_argument("--report", action="store_true", help="also time the figures and report")
    parser.add_argument("--rates", action="store_true", help="rates on many recordings")
    parser.add_argument("--seeds", type=int, default=5, help="recordings per case (--rates)")
    parser.add_argument("--clean", type=int, default=20, help="clean recordings (--rates)")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=1,
        help="seed of the first recording (--rates); runs with far-apart first seeds draw "
        "independent recordings and can run in parallel",
    )
    cases = ["clean", *AMPLITUDES, "detector_time_constant", *PAIRS, *OUTSIDE]
    parser.add_argument(
        "--only", nargs="+", choices=cases, metavar="CASE", help=f"--rates cases: {cases}"
    )
    parser.add_argument(
        "--error-scale",
        type=float,
        default=1.0,
        help="--rates: multiply the spread of every nominal error (robustness)",
    )
    parser.add_argument("--out", help="--rates: write the counts to this JSON file")
    parser.add_argument(
        "--combine", nargs="+", metavar="JSON", help="add up the counts of --out files"
    )
    parser.add_argument("--figure", help="--rates/--combine: the rates figure (PNG)")
    arguments = parser.parse_args()
    if arguments.rates or arguments.combine:
        run_rates(arguments)
        return

    reuse_freed_memory()  # as the diagnose command does
    use_base_pages()
    sky_map = sky.cmb_map(arguments.nside, 3 * arguments.nside - 1, 0.0, 1, 0, 30.8)
    started = time.perf_counter()
    recording = simulate_recording(
        arguments.channel,
        arguments.hours,
        1,
        99,
        sky_map,
        arguments.a2_k,
        EFFECTS[arguments.effect],
    )
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "recording.h5"
        write_recording(path, recording)
        del recording
        recording = read_recording(path)
        print(
            f"{arguments.channel}: {arguments.hours:g} h, {recording.n_samples} samples x "
            f"{recording.n_detectors} detectors, effect {arguments.effect!r}; simulated, written "
            f"and read in {time.perf_counter() - started:.1f} s"
        )
        started = time.perf_counter()
        result = diagnose(recording, sky_map, arguments.a2_k, workers=arguments.workers)
        seconds = time.perf_counter() - started
        samples = recording.n_samples * recording.n_detectors
        print(
            f"diagnose: {seconds:.1f} s ({samples / seconds:.3e} detector-samples/s); found "
            f"{[e['name'] for e in result['effects']]}, chi2 {result['chi2_before']:.4g} -> "
            f"{result['chi2_after']:.4g} (dof {result['dof']})"
        )
        if arguments.report:
            started = time.perf_counter()
            diagnose(
                recording,
                sky_map,
                arguments.a2_k,
                out_dir=Path(folder) / "out",
                workers=arguments.workers,
            )
            print(f"diagnose with report and figures: {time.perf_counter() - started:.1f} s")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"peak RSS of the process: {peak_mb:.0f} MB (target: a one-day pair in <= 60 s with --workers 2)"
    )


if __name__ == "__main__":
    main()
