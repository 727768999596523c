"""Timeline of a Snakemake run: when each job ran, and how busy the cores were.

    snakemake --cores 2
    python benchmarks/timeline.py .snakemake/log/<latest>.snakemake.log --cores 2 \
        --out docs/one_day/timeline.png

Reads the scheduler's own log (a timestamp before every "rule ..."/"localrule ..."
start and every "Finished jobid: N (Rule: ...)" line; one-second resolution), draws
one bar per job (coloured by rule) with the number of running jobs below, and prints
the core utilisation sum(job time x threads) / (wall time x cores) and the fraction
of the wall time during which all cores had a job.
"""

from __future__ import annotations

import argparse
import datetime
import re
from pathlib import Path

import numpy as np

STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
START = re.compile(r"^(?:local)?rule (\w+):$")
JOBID = re.compile(r"^\s+jobid: (\d+)$")
THREADS = re.compile(r"^\s+threads: (\d+)$")
FINISHED = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$")


def parse_jobs(log_path: Path) -> list[dict]:
    """[{rule, jobid, start, end, threads}] with times in seconds from the first job."""
    jobs, running, stamp, pending = [], {}, None, None
    for line in log_path.read_text().splitlines():
        if match := STAMP.match(line):
            stamp = datetime.datetime.strptime(match.group(1), "%a %b %d %H:%M:%S %Y")
        elif match := START.match(line):
            pending = {"rule": match.group(1), "start": stamp, "threads": 1}
        elif pending is not None and (match := THREADS.match(line)):
            pending["threads"] = int(match.group(1))
        elif pending is not None and (match := JOBID.match(line)):
            running[int(match.group(1))] = pending
        elif line.strip() == "" and pending is not None and pending in running.values():
            pending = None
        elif match := FINISHED.match(line):
            job = running.pop(int(match.group(1)), None)
            if job is not None:
                jobs.append({**job, "jobid": int(match.group(1)), "end": stamp})
    if not jobs:
        raise ValueError(f"{log_path}: no finished jobs found (expected a Snakemake log)")
    origin = min(job["start"] for job in jobs)
    for job in jobs:
        job["start"] = (job["start"] - origin).total_seconds()
        job["end"] = (job["end"] - origin).total_seconds()
    return sorted(jobs, key=lambda job: (job["start"], job["jobid"]))


def utilisation(jobs: list[dict], cores: int) -> tuple[float, float, float]:
    """(wall time [s], core utilisation, fraction of the wall time with all cores busy)."""
    wall_s = max(job["end"] for job in jobs)
    busy_core_s = sum((job["end"] - job["start"]) * job["threads"] for job in jobs)
    grid = np.arange(0.0, wall_s, 0.5) + 0.25
    running = np.zeros_like(grid)
    for job in jobs:
        running += job["threads"] * ((grid >= job["start"]) & (grid < job["end"]))
    return wall_s, busy_core_s / (wall_s * cores), float(np.mean(running >= cores))


def plot(jobs: list[dict], cores: int, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rules = list(dict.fromkeys(job["rule"] for job in jobs))
    colours = {rule: plt.cm.tab20(i % 20) for i, rule in enumerate(rules)}
    figure, (bars, counts) = plt.subplots(
        2, 1, figsize=(12, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    for row, job in enumerate(jobs):
        bars.barh(row, job["end"] - job["start"], left=job["start"], color=colours[job["rule"]])
    bars.set_ylabel("job (in order of start)")
    bars.invert_yaxis()
    bars.legend(
        handles=[plt.Rectangle((0, 0), 1, 1, color=colours[r]) for r in rules],
        labels=rules,
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
    )
    wall_s, used, all_busy = utilisation(jobs, cores)
    bars.set_title(
        f"{title}: {len(jobs)} jobs, {wall_s / 60:.1f} min, core utilisation {used:.0%}, "
        f"all {cores} cores busy {all_busy:.0%} of the time",
        fontsize=10,
    )
    grid = np.arange(0.0, wall_s, 0.5)
    running = np.zeros_like(grid)
    for job in jobs:
        running += job["threads"] * ((grid >= job["start"]) & (grid < job["end"]))
    counts.step(grid, running, where="post", color="k")
    counts.axhline(cores, color="tab:red", linestyle="--", label=f"--cores {cores}")
    counts.set_ylim(0, cores + 0.5)
    counts.set_ylabel("threads running")
    counts.set_xlabel("time since the first job [s]")
    counts.legend(fontsize=8)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("log", type=Path, help="a .snakemake/log/*.snakemake.log file")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("timeline.png"))
    parser.add_argument("--title", default="snakemake --cores 2")
    arguments = parser.parse_args()
    jobs = parse_jobs(arguments.log)
    wall_s, used, all_busy = utilisation(jobs, arguments.cores)
    print(
        f"{len(jobs)} jobs in {wall_s:.0f} s; core utilisation {used:.1%}; "
        f"all {arguments.cores} cores busy {all_busy:.1%} of the wall time"
    )
    per_rule: dict[str, list[float]] = {}
    for job in jobs:
        per_rule.setdefault(job["rule"], []).append(job["end"] - job["start"])
    for rule, seconds in per_rule.items():
        print(f"  {rule:22s} {len(seconds):3d} jobs, {sum(seconds):7.0f} s in all")
    plot(jobs, arguments.cores, arguments.out, arguments.title)
    print(f"wrote {arguments.out}")


if __name__ == "__main__":
    main()
