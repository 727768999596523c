"""Rates of the diagnosis on recordings whose effects litebird_sim's own injectors made
(issue 29, item 9).

    python benchmarks/diagnose_lbs_rates.py --channels M1-140 H3-402 --hours 6 --seeds 3 \
        --gap-every 3 --out lbs_rates.json
    python benchmarks/diagnose_lbs_rates.py --combine lbs_rates.json other.json
    python benchmarks/diagnose_lbs_rates.py --strict recordings.txt   # from its stderr lines
    python benchmarks/diagnose_lbs_rates.py --channels H3-402 --only nonlinearity \
        --amplitudes 0.002 0.005 0.01 0.02 --seeds 3 --first-seed 2101   # a ladder

Each recording: a pair of ``--channels`` simulated with random nominal errors
(diagnose.testbed.nominal_errors, as the catalog's rates benchmark) about the channel's
nominal A_2 (the one the diagnosis is told; before 2026-11-28 every channel's recording
held M1-140's 0.26 K) and its own noise seed, then ONE of these applied to its TOD by
litebird_sim's functions (the diagnosis is told nothing):

* ``nonlinearity``: ``non_linearity.apply_quadratic_nonlin_for_one_detector`` with g1 per
  detector drawn by litebird_sim (NonLinParams loc = minus the amplitude, scale 10 % of it);
  expected ``tes_nonlinearity``, g1 within 3 sigma of the drawn value;
* ``linear_gain``: ``apply_gaindrift_for_one_detector`` (LINEAR_GAIN, sigma_drift = the
  amplitude, calibration period longer than the recording: one ramp per detector);
  expected ``gain_drift`` (or the HWP temperature drift with ``gain_drift`` named), its g1
  within 3 sigma of the ramp's half-range over its mean (the drift is relative: the gain
  adjustment takes the mean gain; the half-range alone was 0.25 % high at 1e-2);
* ``thermal_gain``: ``apply_gaindrift_to_tod`` (THERMAL_GAIN, one focal-plane group,
  detector_mismatch 0.1, sigma_drift = the amplitude); expected ``gain_fluctuations`` (or a
  drift of the gain or the HWP emission taking its slow part);
* ``correlated_noise``: a 1/f noise common to the two detectors (knee = the amplitude
  [Hz], the detectors' NET) added to their own: not an effect, no catalog effect may be
  reported (a false alarm otherwise);
* ``clean``: nothing (false alarms).

Every ``--gap-every``-th recording has 10 % of its samples NaN (one stretch at a random
place). Printed per case and amplitude: reported, expected effect ranked first (or named as
look-alike), main parameter within 3 sigma; false alarms. ``--out`` keeps the counts.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.effects import family_of

CASES = {  # case -> (amplitudes, accepted families)
    "nonlinearity": ([1e-3, 3e-3, 1e-2], {"tes_nonlinearity"}),
    "linear_gain": ([1e-3, 3e-3, 1e-2], {"gain_drift"}),
    "thermal_gain": ([3e-5, 1e-4, 3e-4], {"gain_fluctuations"}),
    "correlated_noise": ([0.02, 0.1], set()),
    "clean": ([0.0], set()),
}
DRIFTS = {"gain_drift", "hwp_temperature_drift", "hwpss_slow_modulation"}  # a gain's slow part


def inject(case: str, amplitude: float, recording, rng: np.random.Generator) -> list:
    """Apply ``case`` at ``amplitude`` to ``recording.tod`` with litebird_sim's functions;
    the truth of the main parameter per detector (or [])."""
    import litebird_sim as lbs
    from litebird_sim.non_linearity import apply_quadratic_nonlin_for_one_detector

    tod, rate = recording.tod, recording.sampling_rate_hz
    truth = []
    if case == "nonlinearity":
        params = lbs.NonLinParams(
            sampling_gaussian_loc=-amplitude, sampling_gaussian_scale=0.1 * amplitude
        )
        for k in range(tod.shape[0]):
            before = tod[k].copy()
            apply_quadratic_nonlin_for_one_detector(tod[k], nl_params=params, random=rng)
            # the drawn g1: d_NL - d = g1 d^2
            truth.append(float(np.sum((tod[k] - before) * before**2) / np.sum(before**4)))
    elif case == "linear_gain":
        params = lbs.GainDriftParams(
            drift_type=lbs.GainDriftType.LINEAR_GAIN,
            sigma_drift=amplitude,
            calibration_period_sec=int(2 * tod.shape[1] / rate),
        )
        for k in range(tod.shape[0]):
            gain = np.ones(tod.shape[1])
            lbs.apply_gaindrift_for_one_detector(gain, rate, params, random=rng)
            tod[k] *= gain
            # a ramp is g1 P1(x), x in [-1, 1], relative to the mean gain (the nominal gain
            # adjustment takes the mean): half-range / mean, not the half-range alone
            truth.append(float((gain[-1] - gain[0]) / 2 / gain.mean()))
    elif case == "thermal_gain":
        params = lbs.GainDriftParams(
            drift_type=lbs.GainDriftType.THERMAL_GAIN,
            sigma_drift=amplitude,
            detector_mismatch=0.1,
        )
        lbs.apply_gaindrift_to_tod(
            tod,
            rate,
            params,
            focalplane_attr=np.array(["wafer"] * tod.shape[0]),
            dets_random=[np.random.default_rng(rng.integers(2**32)) for _ in range(tod.shape[0])],
        )
    elif case == "correlated_noise":
        net = np.mean([d["net_ukrts"] for d in recording.detectors]) * 1e-6
        freqs = np.fft.rfftfreq(tod.shape[1], 1 / rate)
        white = rng.standard_normal(tod.shape[1]) * net * np.sqrt(rate)
        shape = np.sqrt(amplitude / np.maximum(freqs, freqs[1]))
        tod += np.fft.irfft(np.fft.rfft(white) * shape, n=tod.shape[1])[None, :]
    return truth


def with_gap(recording, rng: np.random.Generator, fraction: float = 0.1) -> None:
    """NaN over ``fraction`` of the samples, one stretch at a random place."""
    n = recording.tod.shape[1]
    length = int(fraction * n)
    start = int(rng.integers(0, n - length))
    recording.tod[:, start : start + length] = np.nan


def one(support, channel, case, amplitude, seed, arguments, folder) -> dict:
    """Simulate, inject, (gap), write, read back, diagnose: the tallies of one recording."""
    import h5py

    from hwp_tes_systematics.diagnose import read_recording

    started = time.perf_counter()
    rng = np.random.default_rng([seed, 29])
    errors = support.nominal_errors(rng)
    name = f"lbs{seed}.h5"
    a2 = support.nominal(channel)["a2_k"]  # the recording is simulated about it, and told it
    recording, _ = support.recorded_with_errors(
        Path(folder),
        [],
        20_000 + seed,
        errors,
        hours=arguments.hours,
        name=name,
        channel=channel,
        a2_k=a2,
    )
    truth = inject(case, amplitude, recording, rng)
    gapped = arguments.gap_every > 0 and seed % arguments.gap_every == 0
    if gapped:
        with_gap(recording, rng)
    path = Path(folder) / name
    with h5py.File(path, "r+") as handle:  # the injected TOD back into the file
        handle["tod"][...] = recording.tod
    recording = read_recording(path)
    result = diagnose(recording, support.supplied_sky(errors), a2, figures=False)
    tally = score(result, case, truth)
    if arguments.keep:  # the whole diagnosis, to read why a recording scored as it did
        arguments.keep.mkdir(parents=True, exist_ok=True)
        keep = arguments.keep / f"{channel}_{case}_{amplitude:g}_seed{seed}.json"
        keep.write_text(result.to_json())
    names = [family_of(e["name"]) for e in result["effects"]]
    print(
        f"{channel} {case} {amplitude:g} seed {seed}{' (gap)' if gapped else ''}: reported "
        f"{', '.join(names) or '-'}; unexplained {len(result['unexplained'])}; "
        f"{time.perf_counter() - started:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    return tally | {"gapped": int(gapped)}


def score(result: dict, case: str, truth: list) -> dict:
    """The tallies of one diagnosis of a ``case`` recording: ``first`` (an accepted effect
    ranked first), ``look_alike`` (else named as the first effect's look-alike), ``correct``
    (either, or for the thermal gain only drifts of the gain or HWP emission), ``extra``
    (an effect outside the accepted ones and their drifts also reported), and the pulls
    (value - truth) / sigma of the main parameter per detector when ranked first."""
    names = [family_of(e["name"]) for e in result["effects"]]
    accepted = CASES[case][1]
    allowed = accepted | DRIFTS if case == "thermal_gain" else accepted
    top = result["effects"][0] if result["effects"] else None
    first = bool(names) and names[0] in accepted
    named = bool(top) and bool(accepted & {family_of(n) for n in top.get("look_alikes", [])})
    correct = first or named
    if case == "thermal_gain":  # its slow part may be taken as a drift
        correct = correct or bool(names) and set(names) <= allowed
    pulls = []
    if truth and first:
        effect = result["effects"][0]
        main = effect["main_parameters"][0]
        entries = [p for p in effect["parameters"].values() if p["parameter"] == main]
        pulls = [(p["value"] - t) / p["sigma"] for p, t in zip(entries, truth, strict=False)]
    # no nonlinearity found: g1 fitted beside the effects found bounds it (requirement_check);
    # its truth is the injected g1 (0 where none was), so (g1 - truth) / sigma is a pull,
    # and whether |g1| + 2 sigma covers |truth| the bound's coverage
    check = result.get("requirement_check") or {}
    beside = check.get("detectors", []) if check.get("detected") is False else []
    g1_truth = truth if case == "nonlinearity" else [0.0] * len(beside)
    return {
        "beside_pulls": [
            round((d["g1_per_k"] - t) / d["sigma_per_k"], 3)
            for d, t in zip(beside, g1_truth, strict=False)
        ],
        "beside_bounds": [d["bound_per_k"] for d in beside],
        "beside_covered": [
            int(d["bound_per_k"] >= abs(t)) for d, t in zip(beside, g1_truth, strict=False)
        ],
        "n": 1,
        "reported": int(bool(names)),
        "alarm": int(bool(result["mismatch_found"])),
        "correct": int(correct),
        "first": int(first),
        "look_alike": int(named and not first),
        "extra": int(bool(accepted) and bool(set(names) - allowed)),
        "param_checked": int(bool(pulls)),
        "within": int(bool(pulls) and all(abs(p) < 3 for p in pulls)),
        "pulls": [round(p, 3) for p in pulls],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", nargs="+", default=["M1-140", "H3-402"])
    parser.add_argument("--hours", type=float, default=6.0)
    parser.add_argument("--seeds", type=int, default=3, help="recordings per case and amplitude")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--gap-every", type=int, default=3, help="0: no gaps")
    parser.add_argument("--only", nargs="+", choices=sorted(CASES), default=sorted(CASES))
    parser.add_argument(
        "--amplitudes",
        nargs="+",
        type=float,
        help="a ladder of amplitudes instead of each case's own (e.g. g1 [1/K] for nonlinearity)",
    )
    parser.add_argument("--out", type=Path)
    parser.add_argument("--keep", type=Path, metavar="DIR", help="write each diagnosis.json here")
    parser.add_argument(
        "--combine", nargs="+", type=Path, metavar="JSON", help="add up the counts of --out files"
    )
    parser.add_argument(
        "--strict",
        nargs="+",
        type=Path,
        metavar="LINES",
        help="the strict counts of the per-recording lines a run printed (its stderr)",
    )
    arguments = parser.parse_args()
    if arguments.combine:
        print("\n".join(summary(combine(arguments.combine))))
        return
    if arguments.strict:
        lines = [line for path in arguments.strict for line in path.read_text().splitlines()]
        print("\n".join(strict_counts(lines)))
        return
    from hwp_tes_systematics.diagnose import testbed as support

    counts: dict = {"hours": arguments.hours, "cases": {}}
    seed = arguments.first_seed
    with tempfile.TemporaryDirectory() as folder:
        for channel in arguments.channels:
            for case in arguments.only:
                for amplitude in arguments.amplitudes or CASES[case][0]:
                    key = f"{channel} {case} {amplitude:g}"
                    entry = counts["cases"].setdefault(key, {})
                    for _ in range(arguments.seeds):
                        tally = one(support, channel, case, amplitude, seed, arguments, folder)
                        seed += 1
                        add(entry, tally)
                    print(summary_line(key, entry), flush=True)
    if arguments.out:
        arguments.out.write_text(json.dumps(counts, indent=1))


RECORDING_LINE = re.compile(
    r"^(?P<channel>\S+) (?P<case>\S+) (?P<amplitude>\S+) seed \d+( \(gap\))?: "
    r"reported (?P<reported>.*); unexplained (?P<unexplained>\d+); \d+ s$"
)
EXPECTED = {"nonlinearity": "tes_nonlinearity", "linear_gain": "gain_drift"}
EXPECTED["thermal_gain"] = "gain_fluctuations"


def strict_counts(lines: list[str]) -> list[str]:
    """Per case and amplitude, from the recording lines a run prints: how many report the
    expected effect alone and leave nothing in `unexplained` (a null case: nothing at all);
    no drift beside a fluctuation, no look-alike reported in its place."""
    counts: dict = {}
    for line in lines:
        match = RECORDING_LINE.match(line.strip())
        if not match:
            continue
        reported = match["reported"]
        names = [] if reported == "-" else reported.split(", ")
        expected = EXPECTED.get(match["case"])
        alone = names == ([expected] if expected else [])
        key = f"{match['channel']} {match['case']} {match['amplitude']}"
        strict, n = counts.get(key, (0, 0))
        counts[key] = (strict + int(alone and match["unexplained"] == "0"), n + 1)
    out = [f"{key}: strict {s}/{n}" for key, (s, n) in sorted(counts.items())]
    total = [sum(c[i] for c in counts.values()) for i in (0, 1)]
    return [*out, f"strict (the expected effect alone, nothing unexplained): {total[0]}/{total[1]}"]


def combine(paths: list[Path]) -> dict:
    """The counts of several --out files added up per case (one recording length)."""
    counts: dict = {"hours": None, "cases": {}}
    for path in paths:
        part = json.loads(path.read_text())
        if counts["hours"] not in (None, part["hours"]):
            raise SystemExit(
                f"{path}: {part['hours']} h recordings, the others {counts['hours']} h"
            )
        counts["hours"] = part["hours"]
        for key, tally in part["cases"].items():
            entry = counts["cases"].setdefault(key, {})
            add(entry, tally)
    return counts


def add(entry: dict, tally: dict) -> None:
    """Add ``tally`` into ``entry``: counts summed, lists (pulls) joined."""
    for name, value in tally.items():
        entry[name] = entry.get(name, [] if isinstance(value, list) else 0) + value


def summary(counts: dict) -> list[str]:
    """One line per case and amplitude, then the totals against the targets: expected
    effect ranked first or named >= 90 %, parameter within 3 sigma >= 80 %, false alarms
    <= 5 %."""
    lines = [summary_line(key, c) for key, c in sorted(counts["cases"].items())]
    effects = [c for key, c in counts["cases"].items() if CASES[key.split()[1]][1]]
    nulls = [c for key, c in counts["cases"].items() if not CASES[key.split()[1]][1]]

    def total(entries, name):
        return sum(c[name] for c in entries)

    lines.append(
        f"{counts['hours']:g} h recordings: expected effect ranked first or named "
        f"{total(effects, 'correct')}/{total(effects, 'n')} (target >= 90 %); parameter "
        f"within 3 sigma {total(effects, 'within')}/{total(effects, 'param_checked')} "
        f"(target >= 80 %); false alarms {total(nulls, 'alarm')}/{total(nulls, 'n')} "
        f"(target <= 5 %); with a gap: {total(effects + nulls, 'gapped')} of "
        f"{total(effects + nulls, 'n')}"
    )
    if effects and all("first" in c for c in effects):
        pulls = np.concatenate([c["pulls"] for c in effects] + [np.zeros(0)])
        lines[-1] += (
            f"; ranked first {total(effects, 'first')}, look-alike "
            f"{total(effects, 'look_alike')}, with an extra effect {total(effects, 'extra')}"
            + (f"; pulls rms {np.sqrt(np.mean(pulls**2)):.2f}" if pulls.size else "")
        )
    return lines


def summary_line(key: str, c: dict) -> str:
    """A case's counts; the split into ranked first / look-alike / extra effects and the
    pulls where the run recorded them (files before session 23 did not)."""
    case = key.split()[1]
    beside = ""
    if c.get("beside_pulls"):  # runs before the nonlinearity bound (session 31) lack it
        pulls, bounds = np.asarray(c["beside_pulls"]), np.asarray(c["beside_bounds"])
        truth = "the injected g1" if case == "nonlinearity" else "truth 0"
        beside = (
            f"; g1 fitted beside ({truth}): pulls mean {pulls.mean():+.2f} rms "
            f"{np.sqrt(np.mean(pulls**2)):.2f} over {pulls.size}, |g1| + 2 sigma median "
            f"{np.median(bounds):.2g} K^-1"
        )
        if "beside_covered" in c:  # runs before this count (b56a371) lack it
            beside += f", covering |truth| in {sum(c['beside_covered'])}/{pulls.size}"
    if not CASES[case][1]:
        return f"{key}: false alarms {c['alarm']}/{c['n']} ({c['gapped']} with a gap){beside}"
    line = (
        f"{key}: reported {c['reported']}/{c['n']}, expected ranked first or named "
        f"{c['correct']}/{c['n']}, parameter within 3 sigma {c['within']}/{c['param_checked']} "
        f"({c['gapped']} with a gap)"
    )
    if "first" in c:
        line += (
            f"; ranked first {c['first']}, look-alike {c['look_alike']}, with an extra effect "
            f"{c['extra']}"
        )
    if c.get("pulls"):
        pulls = np.asarray(c["pulls"])
        line += f"; pulls mean {pulls.mean():+.2f} rms {np.sqrt(np.mean(pulls**2)):.2f}"
    return line + beside


if __name__ == "__main__":
    main()
