"""The pointing offset's detection threshold [arcmin] for a 6 h and a 24 h pair (issue 29).

    python benchmarks/pointing_threshold.py --hours 6 --offsets 1.5 3 4.5 6 9 --seeds 4 \
        --out docs/diagnosis_rates/pointing_6h.json
    python benchmarks/pointing_threshold.py --hours 24 --offsets 1 2 3 4.5 --seeds 2 \
        --out docs/diagnosis_rates/pointing_24h.json

For each offset size, ``--seeds`` M1-140 pairs (diagnose.testbed, nside-32 CMB sky) with
the detectors rotated by litebird_sim quaternions about a focal-plane direction drawn at
random (the recording keeps the nominal pointing), with nominal errors drawn as the rates
benchmark draws them (A_2, 2f phase, gain, polarisation angle, offsets, noise level and
knee, the supplied sky rescaled and perturbed); and as many clean pairs. Printed per size:
how often a pointing effect is named (top-ranked and at all), how often both fitted
components are within 3 sigma (+0.3 arcmin) of the truth, and on the clean pairs how often
any effect is named (false alarms). The threshold is the smallest size named in >= 90 %.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.effects import family_of
from hwp_tes_systematics.diagnose.testbed import (
    A2_K,
    nominal_errors,
    recorded_with_errors,
    supplied_sky,
)

POINTING = "pointing_offset"


def one(folder: Path, hours: float, offset_arcmin: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    errors = nominal_errors(rng)
    direction = rng.uniform(0, 2 * math.pi)
    truth = {
        "offset_x": offset_arcmin * math.cos(direction),
        "offset_y": offset_arcmin * math.sin(direction),
    }
    effects = [("pointing_offset", truth)] if offset_arcmin > 0 else []
    recording, _ = recorded_with_errors(folder, effects, seed, errors, hours=hours)
    started = time.perf_counter()
    result = diagnose(recording, supplied_sky(errors), A2_K, figures=False)
    wall = time.perf_counter() - started
    families = [family_of(name) for name in result.effect_names]
    row = {
        "hours": hours,
        "offset_arcmin": offset_arcmin,
        "seed": seed,
        "truth": truth,
        "found": result.effect_names,
        "top": families[0] if families else None,
        "named": POINTING in families,
        "wall_s": wall,
    }
    if row["named"]:
        name = next(n for n in result.effect_names if family_of(n) == POINTING)
        fitted = {p: result.parameter(name, p, 0) for p in truth}
        row["fitted"] = {p: [f["value"], f["sigma"]] for p, f in fitted.items()}
        row["within_3_sigma"] = all(
            abs(fitted[p]["value"] - truth[p]) < 3 * fitted[p]["sigma"] + 0.3 for p in truth
        )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=6.0)
    parser.add_argument("--offsets", type=float, nargs="+", default=[1.5, 3.0, 4.5, 6.0, 9.0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=12001)
    parser.add_argument("--out", type=Path, default=None, help="JSON of every recording")
    arguments = parser.parse_args()
    rows = []
    seed = arguments.first_seed
    with tempfile.TemporaryDirectory() as folder:
        for offset in [0.0, *arguments.offsets]:
            for _ in range(arguments.seeds):
                row = one(Path(folder), arguments.hours, offset, seed)
                seed += 1
                rows.append(row)
                print(
                    f"{arguments.hours:g} h, offset {offset:g} arcmin, seed {row['seed']}: "
                    f"{row['found']} ({row['wall_s']:.0f} s)",
                    flush=True,
                )
    print(f"\n{arguments.hours:g} h M1-140 pair, {arguments.seeds} recordings per size:")
    threshold = None
    for offset in [0.0, *arguments.offsets]:
        group = [r for r in rows if r["offset_arcmin"] == offset]
        if offset == 0:
            alarms = sum(bool(r["found"]) for r in group)
            print(f"  clean: any effect named in {alarms}/{len(group)}")
            continue
        top = sum(r["top"] == POINTING for r in group)
        named = sum(r["named"] for r in group)
        within = sum(r.get("within_3_sigma", False) for r in group)
        fitted = f"{within}/{named}" if named else "-"
        print(
            f"  {offset:g} arcmin: top-ranked {top}/{len(group)}, named {named}/{len(group)}, "
            f"both components within 3 sigma {fitted}"
        )
        if threshold is None and top >= 0.9 * len(group):
            threshold = offset
    print(f"  detection threshold (top-ranked in >= 90 %): {threshold} arcmin")
    if arguments.out:
        arguments.out.write_text(
            json.dumps({"threshold_arcmin": threshold, "rows": rows}, indent=1) + "\n"
        )


if __name__ == "__main__":
    main()
