"""Rates of the diagnosis on recordings TOAST 3 made (needs the ``toast`` extra).

    python benchmarks/diagnose_toast_rates.py --per-case 20 --out toast_rates.json

Each recording is written by TOAST's operators (:mod:`hwp_tes_systematics.diagnose.toast_testbed`:
SimSatellite's LiteBIRD scan with a HWP, ScanHealpixMap, SimDipole, SimNoise, SaveHDF5)
and read back by the diagnosis as a user's file would be. Drawn per recording (never
tuned): duration 1-3 h, sampling rate 19 or 31 Hz, HWP 39, 46 or 61 rpm, A_2 0.1-0.4 K,
NET 30-80 uK sqrt(s), knee 10-50 mHz, one pixel (a pair) or, one recording in five,
seven (14 detectors), 2 % of the samples flagged in one recording in three, and the
nominal errors the diagnosis is not told: A_2 given 3 % off, a 2f phase of ~1 deg, a
gain ~1 %, the file's NET ~10 % off the noise drawn. Then one case:

* ``clean``: nothing more (a false alarm is any effect reported or structure left);
* ``nonlinearity``: d -> (1 + g1 d) d, |g1| log-uniform in 2e-3 - 3e-2 K^-1 with a random
  sign, before the gain error; expected ``tes_nonlinearity`` (or its cubic form) first,
  every detector's g1 within 3 sigma of g1 / (1 + gain) (g1 in the recorded units: the
  gain rescales the temperature axis, d_rec = d' + g1 d'^2 / (1 + gain), d' = (1 + gain) d);
* ``gain_drift``: TOAST's ``GainDrifter`` (linear_drift, sigma 3e-3 - 3e-2): each detector
  a ramp 1 + s t / T; expected ``gain_drift`` first, its g1 (the P1 coefficient) within
  3 sigma of s / (2 + s);
* ``both``: the nonlinearity and the gain drift; expected both named, one of them first,
  g1 against g1 / ((1 + gain) (1 + s / 2)) (GainDrifter acts after the nonlinearity, as a
  readout gain would: in the recorded units g1 is divided by the ramp, whose mean the
  diagnosis's gain takes; the diagnosis composes the nonlinearity on the drifted signal,
  so the ramp's change of g1 over the recording, +-s/2, is left to the residual).

Prints one line per recording and, per case, the rates: per recording (every detector's
parameters within 3 sigma) and per parameter; ``--out`` keeps every record, ``--combine``
prints the rates of several such files.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import healpy as hp
import numpy as np

from hwp_tes_systematics.diagnose import diagnose, read_recording
from hwp_tes_systematics.diagnose.testbed import sky_map
from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

CASES = ("clean", "nonlinearity", "gain_drift", "both")
NONLINEARITY_NAMES = ("tes_nonlinearity", "tes_nonlinearity_cubic")


def draw(case: str, rng: np.random.Generator) -> dict:
    """The recording's set-up, nominal errors and injected effect."""
    a2_true = float(rng.uniform(0.1, 0.4))
    setup = {
        "hours": float(rng.uniform(1.0, 3.0)),
        "sample_rate_hz": float(rng.choice([19.0, 31.0])),
        "hwp_rpm": float(rng.choice([39.0, 46.0, 61.0])),
        "a2_k": a2_true,
        "hwpss_phase_rad": float(np.radians(rng.normal(0.0, 1.0))),
        "gain": float(rng.normal(0.0, 0.01)),
        "net_uk_rts": float(rng.uniform(30.0, 80.0)),
        "fknee_mhz": float(rng.uniform(10.0, 50.0)),
        "net_written_factor": float(1.0 + rng.normal(0.0, 0.1)),
        "n_pixels": 7 if rng.random() < 0.2 else 1,
        "flagged_fraction": 0.02 if rng.random() < 1 / 3 else 0.0,
    }
    if case in ("nonlinearity", "both"):
        setup["g1_per_k"] = float(
            rng.choice([-1, 1]) * np.exp(rng.uniform(np.log(2e-3), np.log(3e-2)))
        )
    if case in ("gain_drift", "both"):
        setup["gain_drift_sigma"] = float(np.exp(rng.uniform(np.log(3e-3), np.log(3e-2))))
    a2_told = a2_true * (1.0 + rng.normal(0.0, 0.03))
    return {"setup": setup, "a2_told_k": float(a2_told)}


def within(parameters: dict, name: str, truth: dict) -> list[float]:
    """Pulls (value - truth) / sigma of ``name`` per detector."""
    return [
        (p["value"] - truth[p["detector"]]) / p["sigma"]
        for p in parameters.values()
        if p["parameter"] == name and p.get("sigma")
    ]


def fitted(parameters: dict, name: str) -> dict:
    """{detector: [value, sigma]} of ``name``."""
    return {
        p["detector"]: [p["value"], p.get("sigma")]
        for p in parameters.values()
        if p["parameter"] == name
    }


def score(case: str, result: dict, setup: dict, truth: dict) -> dict:
    effects = result["effects"]
    names = [effect["name"] for effect in effects]
    record = {"reported": names, "unexplained": len(result.get("unexplained", []))}
    if case == "clean":
        record["false_alarm"] = bool(names or record["unexplained"])
        return record
    expected = []
    if case in ("nonlinearity", "both"):
        expected.append("nonlinearity")
    if case in ("gain_drift", "both"):
        expected.append("gain_drift")
    found = {}
    for label in expected:
        wanted = NONLINEARITY_NAMES if label == "nonlinearity" else ("gain_drift",)
        match = [effect for effect in effects if effect["name"] in wanted]
        if not match:
            found[label] = None
            continue
        record[f"{label}_fitted"] = fitted(match[0]["parameters"], "g1")
        if label == "nonlinearity":
            slopes = truth.get("gain_drift_slope", dict.fromkeys(truth["detectors"], 0.0))
            g1 = {
                k: setup["g1_per_k"] / ((1 + setup["gain"]) * (1 + s / 2))
                for k, s in slopes.items()
            }
            pulls = within(match[0]["parameters"], "g1", g1)
        else:
            slopes = truth["gain_drift_slope"]
            pulls = within(
                match[0]["parameters"], "g1", {k: s / (2 + s) for k, s in slopes.items()}
            )
        found[label] = pulls
    record["named"] = all(found[label] is not None for label in expected)
    allowed = {"nonlinearity": NONLINEARITY_NAMES, "gain_drift": ("gain_drift",)}
    record["first"] = bool(names) and any(names[0] in allowed[label] for label in expected)
    pulls = [p for label in expected for p in (found[label] or [])]
    record["pulls"] = [round(p, 2) for p in pulls]
    record["within_3_sigma"] = record["named"] and all(abs(p) < 3 for p in pulls)
    return record


def one(case: str, seed: int, sky_fits: Path, folder: Path) -> dict:
    rng = np.random.default_rng([seed, CASES.index(case)])
    drawn = draw(case, rng)
    truth: dict = {}
    path = write_toast_recording(folder, sky_fits, seed=seed, truth=truth, **drawn["setup"])
    recording = read_recording(path)
    truth["detectors"] = recording.detector_names
    start = time.monotonic()
    result = diagnose(recording, sky_map(), drawn["a2_told_k"], figures=False).to_dict()
    record = {"case": case, "seed": seed, **drawn, "seconds": round(time.monotonic() - start, 1)}
    record["truth"] = truth
    record.update(score(case, result, drawn["setup"], truth))
    path.unlink()
    return record


def summary(records: list[dict]) -> list[str]:
    lines = []
    for case in CASES:
        rows = [r for r in records if r["case"] == case]
        if not rows:
            continue
        n = len(rows)
        if case == "clean":
            alarms = sum(r["false_alarm"] for r in rows)
            lines.append(f"{case:13s} {n:3d} recordings: false alarms {alarms}/{n}")
        else:
            first = sum(r["first"] for r in rows)
            named = sum(r["named"] for r in rows)
            inside = sum(r["within_3_sigma"] for r in rows)
            pulls = [p for r in rows for p in r["pulls"]]
            inside_p = sum(abs(p) < 3 for p in pulls)
            extra = sum(len(r["reported"]) > (2 if case == "both" else 1) for r in rows)
            lines.append(
                f"{case:13s} {n:3d} recordings: ranked first {first}/{n}, every effect named "
                f"{named}/{n}, another effect named too {extra}/{n}; parameters within 3 "
                f"sigma: every one of the recording {inside}/{n}, "
                f"per parameter {inside_p}/{len(pulls)}"
            )
    seconds = [r["seconds"] for r in records]
    lines.append(
        f"diagnosis time per recording: median {np.median(seconds):.1f} s, max {max(seconds):.1f} s"
    )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--per-case", type=int, default=20, help="recordings per case")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--only", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--out", type=Path)
    parser.add_argument("--combine", nargs="+", type=Path, metavar="JSON")
    arguments = parser.parse_args()
    if arguments.combine:
        records = [r for path in arguments.combine for r in json.loads(path.read_text())]
        print("\n".join(summary(records)))
        return
    records = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        sky_fits = folder / "sky.fits"
        hp.write_map(sky_fits, sky_map(), dtype=np.float64)
        for case in arguments.only:
            for seed in range(arguments.first_seed, arguments.first_seed + arguments.per_case):
                record = one(case, seed, sky_fits, folder / f"{case}_{seed}")
                records.append(record)
                print(json.dumps(record), file=sys.stderr, flush=True)
                if arguments.out:
                    arguments.out.write_text(json.dumps(records, indent=1) + "\n")
    print("\n".join(summary(records)))


if __name__ == "__main__":
    main()
