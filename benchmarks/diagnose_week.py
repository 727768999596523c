"""A recording longer than memory allows, diagnosed end to end (issue 29, item 7).

    python benchmarks/diagnose_week.py --days 7 --memory-gb 16 --out week

Simulates an M1-140 pair (the PTEP sampling rate, 31 Hz) with a TES nonlinearity
(``--g1``) day by day (diagnose.testbed's sky and nominal A_2, each day its own noise
stream and start time) into one litebird_sim HDF5 file, then runs the command line a user
runs, ``python -m hwp_tes_systematics diagnose FILE --sky SKY --out DIR --memory-gb M``,
in its own process. Printed: the file's size, the segments the diagnosis chose, what it
found, the combined g1 against the truth, its wall time and peak resident memory
(against the budget).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import astropy.time
import h5py
import healpy as hp
import numpy as np

from hwp_tes_systematics.diagnose.recording import DEFAULT_START_TDB, write_recording
from hwp_tes_systematics.diagnose.simulate import _simulated_base, simulate_recording
from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, sky_map


def simulate_days(path: Path, days: int, g1: float, seed: int, day_hours: float = 24.0) -> None:
    """One file of ``days`` consecutive days (``day_hours`` each), simulated and written one
    day at a time."""
    start = astropy.time.Time(DEFAULT_START_TDB, scale="tdb")
    effects = [("tes_nonlinearity", {"g1": g1})]
    handle = None
    try:
        for day in range(days):
            day_start = (start + astropy.time.TimeDelta(day * day_hours * 3600, format="sec")).isot
            recording = simulate_recording(
                CHANNEL,
                day_hours,
                MASTER_SEED,
                seed * 1000 + day,
                sky_map(),
                A2_K,
                effects,
                day_start,
            )
            n_det, n = recording.tod.shape
            if handle is None:  # the layout and metadata of the first day's file
                first = path.with_suffix(".day0.h5")
                write_recording(first, recording)
                handle = h5py.File(path, "w")
                with h5py.File(first) as day0:
                    tod = handle.create_dataset("tod", (n_det, days * n), dtype="f8")
                    for key, value in day0["tod"].attrs.items():
                        tod.attrs[key] = value
                first.unlink()
                handle.create_dataset("pointings", (n_det, days * n, 3), dtype="f8")
                handle.create_dataset("hwp_angle", (days * n,), dtype="f8")
            part = slice(day * n, (day + 1) * n)
            handle["tod"][:, part] = recording.tod
            handle["pointings"][:, part] = recording.pointings_ecl
            handle["hwp_angle"][part] = recording.hwp_angle_rad
            print(f"day {day + 1}/{days} simulated", flush=True)
            del recording
            _simulated_base.cache_clear()  # a day's pointing is not needed again
    finally:
        if handle is not None:
            handle.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=7)
    parser.add_argument("--g1", type=float, default=-3e-3, help="injected g1 [1/K]")
    parser.add_argument("--memory-gb", type=float, default=16.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--day-hours", type=float, default=24.0, help="a quick check: shorter days")
    parser.add_argument("--out", type=Path, required=True)
    arguments = parser.parse_args()
    arguments.out.mkdir(parents=True, exist_ok=True)
    path = arguments.out / "recording.h5"
    sky_path = arguments.out / "sky.fits"
    hp.write_map(sky_path, sky_map(), overwrite=True, dtype=np.float64)
    started = time.perf_counter()
    simulate_days(path, arguments.days, arguments.g1, arguments.seed, arguments.day_hours)
    print(f"simulated in {time.perf_counter() - started:.0f} s: {path.stat().st_size / 1e9:.2f} GB")

    command = [sys.executable, "-m", "hwp_tes_systematics", "diagnose", str(path)]
    command += ["--sky", str(sky_path), "--out", str(arguments.out / "diagnosis")]
    command += ["--memory-gb", str(arguments.memory_gb)]
    started = time.perf_counter()
    subprocess.run(command, check=True)
    wall_s = time.perf_counter() - started
    peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 2**30
    result = json.loads((arguments.out / "diagnosis" / "diagnosis.json").read_text())
    segments = result.get("segments", [])
    print(
        f"\n{arguments.days} x {arguments.day_hours:g} h, 2 detectors at {result['recording']['sampling_rate_hz']:g} Hz: "
        f"{len(segments)} segment(s) of {segments[0]['duration_s'] / 3600:.3g} h"
        if segments
        else "diagnosed at once"
    )
    print(
        f"found: {[e['name'] for e in result['effects']]}; unexplained: {len(result['unexplained'])}"
    )
    for segment in segments:
        print(
            f"  segment {segment['segment']}: {segment['effects']}, {segment['unexplained']} unexplained"
        )
    for effect in result["effects"]:
        if effect["name"] != "tes_nonlinearity":
            continue
        for name, entry in effect["parameters"].items():
            pull = (entry["value"] - arguments.g1) / entry["sigma"]
            print(
                f"  {name} = {entry['value']:.5g} +- {entry['sigma']:.2g} (truth {arguments.g1:g}, "
                f"{pull:+.1f} sigma; segments consistent: p = {entry.get('consistency_p', 1):.2g})"
            )
    print(
        f"diagnosis: {wall_s / 60:.1f} min wall, peak RSS {peak_gib:.2f} GiB "
        f"(budget {arguments.memory_gb:g} GiB)"
    )


if __name__ == "__main__":
    main()
