"""What diagnosing a recording costs in memory and time, per detector-sample.

    python benchmarks/diagnose_memory.py --hours 2 6

For each duration, in a fresh process: an M1-140 pair with a nonlinearity (g1 = -3e-3)
simulated (diagnose.testbed), written and read back, then diagnosed; printed: samples per
detector, the peak RSS before and after the diagnosis, its wall time, what it found; last
the slope of the diagnosis's memory per detector-sample between the shortest and the
longest (the figure behind recording.DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

ONE = """
import json, resource, sys, tempfile, time
from pathlib import Path
from hwp_tes_systematics.diagnose import testbed
hours = float(sys.argv[1])
with tempfile.TemporaryDirectory() as folder:
    recording, _ = testbed.recorded(Path(folder), [("tes_nonlinearity", {"g1": -3e-3})], 99, hours=hours)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    started = time.perf_counter()
    result = testbed.run(recording, figures=False)
    wall = time.perf_counter() - started
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"hours": hours, "samples": recording.tod.size, "before": before,
                  "peak": peak, "wall_s": wall, "found": result.effect_names}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, nargs="+", default=[2.0, 6.0])
    arguments = parser.parse_args()
    rows = []
    for hours in arguments.hours:
        out = subprocess.run(
            [sys.executable, "-c", ONE, str(hours)], check=True, capture_output=True, text=True
        )
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"{row['hours']:g} h: {row['samples']} detector-samples, peak RSS "
            f"{row['before'] / 2**20:.0f} MiB before the diagnosis, {row['peak'] / 2**20:.0f} MiB "
            f"after; diagnosis {row['wall_s']:.1f} s; found {row['found']}"
        )
    if len(rows) > 1:
        first, last = rows[0], rows[-1]
        grown = (last["peak"] - last["before"]) - (first["peak"] - first["before"])
        slope = grown / (last["samples"] - first["samples"])
        print(f"diagnosis memory: {slope:.0f} B per detector-sample")


if __name__ == "__main__":
    main()
