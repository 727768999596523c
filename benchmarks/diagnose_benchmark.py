"""Benchmark of the diagnosis: one recording of one detector pair, diagnosed end to end.

    python benchmarks/diagnose_benchmark.py --hours 24 --nside 64 --effect tes_nonlinearity

Simulates the recording (sky + dipole + HWPSS + noise, optionally one injected effect)
with litebird_sim, writes it to HDF5 and reads it back (not timed), then times
``diagnose`` (nominal model, residual, noise estimate, locate, stepwise fit) without
and with the figures/report. Prints the wall time, the detector-samples per second and
the peak resident memory. Target: a one-day recording at 31 Hz in under 2 minutes on
2 cores.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose import read_recording, simulate_recording, write_recording
from hwp_tes_systematics.diagnose.report import diagnose

EFFECTS = {
    "none": [],
    "tes_nonlinearity": [("tes_nonlinearity", {"g1": -0.04})],
    "detector_time_constant": [("detector_time_constant", {"tau": 3e-3})],
    "glitches": [("glitches", {"events": [(0, 3600.0 * h + 100.0, 3e-3, 0.1) for h in range(20)]})],
    "noise_mismatch": [("noise_mismatch", {"net_ukrts": 60.0, "fknee_mhz": 50.0})],
}


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
    arguments = parser.parse_args()

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
    print(f"peak RSS of the process: {peak_mb:.0f} MB (target: one day in < 120 s on 2 cores)")


if __name__ == "__main__":
    main()
