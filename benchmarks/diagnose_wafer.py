"""Cost of diagnosing a wafer: a TOAST recording of many detectors through the command a
user runs, ``python -m hwp_tes_systematics diagnose``, within a memory budget.

    python benchmarks/diagnose_wafer.py --pixels 37 --hours 6 --rate 31 --memory-gb 16

Writes one TOAST observation (``toast_testbed.write_toast_recording``: a hexagon of
``--pixels`` pixels, two detectors each, split in ``--wafers`` wafers; the HWPSS at
``--a2`` K_CMB and a TES nonlinearity ``--g1`` [1/K] in every detector; TOAST's 1/f noise;
with ``--drift-sigma`` TOAST's slow gain drift beside it, common to each wafer with a
part per detector; with ``--line-step-detectors N`` a bias line's step, an offset
``--line-step-offset-k`` in the first N detectors at ``--line-step-at`` of the recording)
and the sky it scans, then runs the command in a child process with
``--memory-gb`` (a recording whose diagnosis would not fit is diagnosed in segments). Prints the
detectors, samples, wall time, the child's peak resident memory, the segments and the
effects reported. Targets (the wafer diagnosis issue): 64 detectors for 6 hours at 31 Hz
in at most 15 minutes within 16 GB on this machine.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import healpy as hp
import numpy as np

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pixels", type=int, default=37, help="hexagon pixels: 1, 7, 19, 37")
    parser.add_argument("--wafers", type=int, default=2)
    parser.add_argument(
        "--use-pixels", type=int, help="only the hexagon's first N pixels (32 of 37: 64 detectors)"
    )
    parser.add_argument("--hours", type=float, default=6.0)
    parser.add_argument("--rate", type=float, default=31.0, help="sampling rate [Hz]")
    parser.add_argument("--a2", type=float, default=0.264, help="HWPSS 2f amplitude [K_CMB]")
    parser.add_argument("--g1", type=float, default=-0.04, help="TES nonlinearity [1/K]")
    parser.add_argument(
        "--drift-sigma",
        type=float,
        default=0.0,
        help="TOAST GainDrifter slow_drift beside the nonlinearity (its sigma; 0: none)",
    )
    parser.add_argument(
        "--drift-mismatch", type=float, default=0.5, help="the drift's part per detector"
    )
    parser.add_argument(
        "--line-step-detectors",
        type=int,
        default=0,
        help="a bias line's step in the first N detectors (0: none)",
    )
    parser.add_argument(
        "--line-step-offset-k", type=float, default=5e-4, help="the line's offset step [K]"
    )
    parser.add_argument(
        "--line-step-at", type=float, default=0.4, help="its time, a fraction of the recording"
    )
    parser.add_argument("--memory-gb", type=float, default=16.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--keep", help="write the recording and the report here (kept)")
    parser.add_argument(
        "--summary-of", type=Path, metavar="DIR", help="print the lines of DIR/diagnosis.json only"
    )
    arguments = parser.parse_args()
    if arguments.summary_of:  # a kept diagnosis, read again
        result = json.loads((arguments.summary_of / "diagnosis.json").read_text())
        print("\n".join(summary(result, arguments.g1)))
        return

    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(arguments.keep or scratch)
        folder.mkdir(parents=True, exist_ok=True)
        sky_fits = folder / "sky.fits"
        n_samples = round(arguments.hours * 3600 * arguments.rate)
        line_first = round(arguments.line_step_at * n_samples)
        steps = [
            (detector, line_first, arguments.line_step_offset_k, 0.0)
            for detector in range(arguments.line_step_detectors)
        ]
        hp.write_map(sky_fits, sky.cmb_map(64, 191, 0.0, 1, 0, 30.8), dtype=np.float64)
        started = time.perf_counter()
        path = write_toast_recording(
            folder,
            sky_fits,
            hours=arguments.hours,
            seed=arguments.seed,
            n_pixels=arguments.pixels,
            wafers=arguments.wafers,
            use_pixels=arguments.use_pixels,
            sample_rate_hz=arguments.rate,
            a2_k=arguments.a2,
            g1_per_k=arguments.g1,
            gain_drift_sigma=arguments.drift_sigma,
            gain_drift_mode="slow_drift",
            gain_drift_mismatch=arguments.drift_mismatch,
            readout_steps=steps or None,
        )
        n_det = 2 * min(arguments.pixels, arguments.use_pixels or arguments.pixels)
        print(
            f"TOAST recording: {n_det} detectors x {arguments.hours:g} h at {arguments.rate:g} Hz "
            f"({n_det * n_samples:.3g} detector-samples), written in "
            f"{time.perf_counter() - started:.0f} s",
            flush=True,
        )
        out = folder / "diagnosis"
        command = [
            sys.executable,
            "-m",
            "hwp_tes_systematics",
            "diagnose",
            str(path),
            "--sky",
            str(sky_fits),
            "--a2",
            str(arguments.a2),
            "--memory-gb",
            str(arguments.memory_gb),
            "--out",
            str(out),
        ]
        print("$", " ".join(command[1:]), flush=True)
        started = time.perf_counter()
        subprocess.run(command, check=True)
        seconds = time.perf_counter() - started
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20
        result = json.loads((out / "diagnosis.json").read_text())
        segments = result.get("segments")
        names = [effect["name"] for effect in result.get("effects", [])]
        print(
            f"diagnose: {seconds:.0f} s ({seconds / 60:.1f} min; "
            f"{n_det * n_samples / seconds:.3g} detector-samples/s), peak RSS {peak_gb:.1f} GB "
            f"(budget {arguments.memory_gb:g} GB), "
            f"{len(segments) if segments else 'no'} segments; effects {names}"
        )
        print("\n".join(summary(result, arguments.g1)))
        if steps:
            print(steps_summary(result, line_first / arguments.rate, len(steps)))


def steps_summary(result: dict, line_time_s: float, n_line: int) -> str:
    """The readout steps reported against a line's step in the first ``n_line`` detectors at
    ``line_time_s``: how many of its detectors have a step within 60 s, their time pulls,
    and the steps reported elsewhere."""
    steps = next((e for e in result["effects"] if e["name"] == "readout_steps"), None)
    if steps is None:
        return f"readout_steps not reported (a line of {n_line} detectors at {line_time_s:.0f} s)"
    times = [p for p in steps["parameters"].values() if p["parameter"] == "time"]
    near = [p for p in times if abs(p["value"] - line_time_s) <= 60.0]
    pulls = [(p["value"] - line_time_s) / p["sigma"] for p in near if p.get("sigma")]
    return (
        f"readout_steps: {len({p['detector'] for p in near})} of the line's {n_line} detectors "
        f"stepped within 60 s of {line_time_s:.0f} s (time pulls "
        f"{', '.join(f'{x:+.1f}' for x in pulls)}), {len(times) - len(near)} steps elsewhere"
    )


def summary(result: dict, g1_per_k: float) -> list[str]:
    """Lines of a wafer's diagnosis.json: each effect's segments and look-alikes, and the
    fitted g1 against the injected ``g1_per_k`` (pulls per detector)."""
    lines = []
    for effect in result["effects"]:
        line = f"{effect['name']}: named in segments {effect.get('segments', 'all')}"
        for pair in effect.get("look_alikes_across_segments", []):
            other = next(name for name in pair["effects"] if name != effect["name"])
            line += (
                f"; look-alike {other} (segments {pair['segments']}, Delta BIC summed "
                f"{pair['preference_delta_bic']:+.1f}"
            )
            if "preference_final_delta_bic" in pair:  # the swaps under each final noise
                per_segment = {**pair["final_delta_bic_per_segment"][0]}
                per_segment.update(
                    {i: -v for i, v in pair["final_delta_bic_per_segment"][1].items()}
                )
                line += (
                    f", under the final noise {pair['preference_final_delta_bic']:+.1f}: "
                    + ", ".join(f"{i} {v:+.1f}" for i, v in sorted(per_segment.items()))
                )
            line += f"; < 0: {pair['effects'][0]})"
        lines.append(line)
    nonlinearity = next((e for e in result["effects"] if e["name"] == "tes_nonlinearity"), None)
    if nonlinearity is not None:
        pulls = {
            key.removeprefix("g1[").removesuffix("]"): (entry["value"] - g1_per_k) / entry["sigma"]
            for key, entry in nonlinearity["parameters"].items()
            if key.startswith("g1[") and entry.get("sigma")
        }
        values = np.array(list(pulls.values()))
        worst = max(pulls, key=lambda name: abs(pulls[name]))
        lines.append(
            f"g1 against the injected {g1_per_k:g} /K: {values.size} detectors, pulls mean "
            f"{values.mean():+.2f} +- {values.std(ddof=1) / np.sqrt(values.size):.2f}, sd "
            f"{values.std(ddof=1):.2f}, within 3 sigma {np.sum(np.abs(values) <= 3)}/"
            f"{values.size} (largest {worst} {pulls[worst]:+.2f})"
        )
    return lines


if __name__ == "__main__":
    main()
