"""Are two runs' results the same? For a restructuring that must not change behaviour.

    python benchmarks/same_results.py BEFORE/results AFTER/results [--rtol 1e-9]
    python benchmarks/same_results.py BEFORE AFTER --json   # every *.json of two folders

Compares, in the two ``results/`` folders, ``requirement.json`` and
``diagnose/example/diagnosis.json`` (with ``--json``: every ``*.json`` of the two folders,
e.g. the diagnoses of ``diagnose_snapshot.py``) leaf by leaf (numbers to ``--rtol`` of their size,
everything else exactly; ``config_sha256``, which hashes the configuration, skipped) and
``delta_r.csv`` column by column. Prints, per file, the leaves compared, how many are
identical, the largest relative difference and every leaf beyond the tolerance; exits 1
if any is beyond it or a file or key is missing on one side.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import pandas as pd

SKIPPED = {"config_sha256", "source"}  # leaf names not compared (a hash, a file path)


def leaves(value, prefix=""):
    """{'a/b/0': leaf} of a JSON value."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            out.update(leaves(item, f"{prefix}/{key}"))
        return out
    if isinstance(value, list):
        out = {}
        for index, item in enumerate(value):
            out.update(leaves(item, f"{prefix}/{index}"))
        return out
    return {prefix: value}


def compare(before: dict, after: dict, rtol: float) -> tuple[int, int, float, list[str]]:
    """(leaves compared, identical, largest relative difference, problems)."""
    problems, identical, largest = [], 0, 0.0
    keys = [k for k in sorted(set(before) | set(after)) if k.rsplit("/", 1)[-1] not in SKIPPED]
    for key in keys:
        if key not in before or key not in after:
            problems.append(f"{key}: only in {'after' if key not in before else 'before'}")
            continue
        a, b = before[key], after[key]
        if a == b or (
            isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
        ):
            identical += 1
            continue
        numbers = all(isinstance(x, int | float) and not isinstance(x, bool) for x in (a, b))
        if numbers:
            relative = abs(a - b) / max(abs(a), abs(b))
            largest = max(largest, relative)
            if relative > rtol:
                problems.append(f"{key}: {a!r} -> {b!r} (relative {relative:.2g})")
        else:
            problems.append(f"{key}: {a!r} -> {b!r}")
    return len(keys), identical, largest, problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--rtol", type=float, default=1e-9)
    parser.add_argument("--json", action="store_true", help="every *.json of the two folders")
    arguments = parser.parse_args()
    failed = False
    names = ("requirement.json", "diagnose/example/diagnosis.json", "delta_r.csv")
    if arguments.json:
        folders = (arguments.before, arguments.after)
        names = sorted({p.name for folder in folders for p in folder.glob("*.json")})
    for name in names:
        paths = [arguments.before / name, arguments.after / name]
        if not all(p.is_file() for p in paths):
            print(f"{name}: missing in {[str(p) for p in paths if not p.is_file()]}")
            failed = True
            continue
        if name.endswith(".csv"):
            tables = [pd.read_csv(p) for p in paths]
            before, after = ({f"{c}/{i}": v for c in t for i, v in enumerate(t[c])} for t in tables)
        else:
            before, after = (leaves(json.loads(p.read_text())) for p in paths)
        count, identical, largest, problems = compare(before, after, arguments.rtol)
        print(
            f"{name}: {count} leaves, {identical} identical, largest relative difference "
            f"{largest:.2g}, {len(problems)} beyond {arguments.rtol:g}"
        )
        for problem in problems[:20]:
            print(f"  {problem}")
        failed |= bool(problems)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
