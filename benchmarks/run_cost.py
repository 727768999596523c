"""What a workflow run cost, against its targets, and what a larger grid would cost.

    snakemake --cores 2 --configfile config/one_year.yaml config/nside512.yaml
    python benchmarks/run_cost.py . --cores 2 --wall-hours 2.5 --job-memory-gb 20 \
        --disk-gb 50 --scale-seeds 100

Reads the run folder's Snakemake log (the latest, or ``--log``; every job's start and end,
one-second resolution, as benchmarks/timeline.py; a run resumed after a stop gives the log
of each part, and its wall time is their sum), the rules' benchmark files
(``results/benchmarks/``: peak resident memory and CPU time per job) and the size of
``results/``. Prints, as Markdown: per rule the jobs, their summed wall time and CPU
time, the longest job and the peak memory; the run's wall time, core-hours, CPU hours
and disk; each target met or missed. On cores shared with other work the wall time
overstates the run's cost: the CPU time over the cores is then the measure (a lower
bound of an idle machine's wall time: perfect packing).
``--scale-seeds N``: the same grid with N seeds instead of the run's, per rule: the jobs
of a per-seed rule (component_separation, residual_spectra, likelihood) times N / seeds,
the per-channel seed jobs (map_domain_alms, pair_maps) likewise (their shared operators
counted N / seeds times too: an upper bound), the fixed passes and the rest once.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
from pathlib import Path

import pandas as pd
from timeline import parse_jobs

SEED_SCALED = {"component_separation", "residual_spectra", "likelihood", "map_domain_alms"}
SEED_SCALED |= {"pair_maps"}


def benchmark_figures(root: Path) -> tuple[dict[str, float], dict[str, float]]:
    """({rule: largest max_rss over its jobs [GB]}, {rule: summed cpu_time [h]}) from a
    run's benchmark folder (a job's file holds one row per run of it: the last is kept)."""
    peaks, cpu_h = {}, collections.defaultdict(float)
    for path in root.rglob("*.tsv"):
        rule = path.parent.name if path.parent != root else path.stem
        last = pd.read_csv(path, sep="\t").iloc[-1]
        peaks[rule] = max(peaks.get(rule, 0.0), float(last["max_rss"]) / 1024)
        cpu_h[rule] += float(last["cpu_time"]) / 3600
    return peaks, dict(cpu_h)


def disk_gb(folder: Path) -> float:
    result = subprocess.run(["du", "-sb", str(folder)], capture_output=True, text=True, check=True)
    return int(result.stdout.split()[0]) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the run's folder (holding results/, .snakemake/)")
    parser.add_argument(
        "--log", type=Path, nargs="+", help="Snakemake log(s), one per part (default: the latest)"
    )
    parser.add_argument(
        "--benchmarks",
        type=Path,
        help="the benchmark files (default: the run's results/benchmarks; a copy, when a "
        "later run in the same folder rewrote them)",
    )
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--wall-hours", type=float, help="target: wall time of the run")
    parser.add_argument("--job-memory-gb", type=float, help="target: peak memory of any job")
    parser.add_argument("--disk-gb", type=float, help="target: size of results/")
    parser.add_argument("--seeds", type=int, help="the run's seeds (default: from the jobs)")
    parser.add_argument("--scale-seeds", type=int, help="project the grid to this many seeds")
    arguments = parser.parse_args()
    logs = arguments.log or [max((arguments.run / ".snakemake" / "log").glob("*.snakemake.log"))]
    parts = [parse_jobs(log) for log in logs]
    jobs = [job for part in parts for job in part]
    wall_s = sum(max(job["end"] for job in part) for part in parts)
    per_rule = collections.defaultdict(list)
    for job in jobs:
        per_rule[job["rule"]].append((job["end"] - job["start"], job["threads"]))
    peaks, cpu_h = benchmark_figures(
        arguments.benchmarks or arguments.run / "results" / "benchmarks"
    )
    seeds = arguments.seeds or len(per_rule.get("component_separation", [])) or 1
    names = ", ".join(log.name for log in logs)
    print(f"run {arguments.run} (log {names}), {len(jobs)} jobs, {seeds} seeds")
    print("| rule | jobs | core-hours | CPU hours | longest job [min] | peak memory [GB] |")
    print("|---|---|---|---|---|---|")
    total_core_h = 0.0
    scaled_core_h = 0.0
    scale = (arguments.scale_seeds or seeds) / seeds
    for rule, times in sorted(per_rule.items(), key=lambda item: -sum(w * t for w, t in item[1])):
        core_h = sum(wall * threads for wall, threads in times) / 3600
        total_core_h += core_h
        scaled_core_h += core_h * (scale if rule in SEED_SCALED else 1.0)
        peak = f"{peaks[rule]:.1f}" if rule in peaks else "-"
        cpu = f"{cpu_h[rule]:.2f}" if rule in cpu_h else "-"
        longest_min = max(wall for wall, _ in times) / 60
        print(f"| {rule} | {len(times)} | {core_h:.2f} | {cpu} | {longest_min:.1f} | {peak} |")
    size_gb = disk_gb(arguments.run / "results")
    peak_gb = max(peaks.values(), default=float("nan"))
    total_cpu_h = sum(cpu_h.values())
    print(
        f"wall time {wall_s / 3600:.2f} h on {arguments.cores} cores ({len(parts)} part(s)); "
        f"{total_core_h:.2f} core-hours (utilisation "
        f"{total_core_h * 3600 / (wall_s * arguments.cores):.0%}); {total_cpu_h:.2f} CPU hours "
        f"(jobs with a benchmark file), {total_cpu_h / arguments.cores:.2f} h on "
        f"{arguments.cores} idle cores at best; peak job memory {peak_gb:.1f} GB; "
        f"results/ {size_gb:.1f} GB"
    )
    for name, value, target in (
        ("wall time [h]", wall_s / 3600, arguments.wall_hours),
        ("peak job memory [GB]", peak_gb, arguments.job_memory_gb),
        ("results/ [GB]", size_gb, arguments.disk_gb),
    ):
        if target is not None:
            verdict = "met" if value <= target else "MISSED"
            print(f"target {name} <= {target:g}: {value:.2f} ({verdict})")
    if arguments.scale_seeds:
        print(
            f"the same grid with {arguments.scale_seeds} seeds: ~{scaled_core_h:.1f} core-hours "
            f"(per-seed rules x {scale:g}; an upper bound: the seed jobs' shared operators "
            f"scaled too), ~{scaled_core_h / arguments.cores:.1f} h on {arguments.cores} cores"
        )


if __name__ == "__main__":
    main()
