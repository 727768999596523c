"""Scaling of one pair_maps job with the mission duration and the map resolution, and the
extrapolation to the paper's grid in core-hours.

    python benchmarks/scaling.py --days 1 7 30 --nsides 64 128 256 512

Each point runs the job path (TOD + 2f removal + notch + binning of d, the two g1
templates and the CMB and foreground references, as a pair_maps job) of one M1-140 pair
in its own process on one thread, with one-day chunks. Prints a Markdown table: wall
time, ns per detector-sample, resident memory after the first and the last chunk, and
the process peak. The paper's grid is then 22 channels x 100 seeds x one year of two
detectors at each channel's sampling rate, at the measured ns per detector-sample of
the largest nside (the other stages are small next to it: see the README).
"""

from __future__ import annotations

import argparse
import multiprocessing

from common import pair_setup, peak_rss_mb, timed_accumulate, warm_up

YEAR_DAYS = 365.25


def one_point(channel, days, nside, threads, queue):
    warm_up(channel, nside, threads, "keshner")
    simulator, settings, sky_map = pair_setup(channel, days * 86400.0, nside, threads)
    rss_mb = []
    _, seconds, clock = timed_accumulate(
        simulator, settings, sky_map, "job", on_chunk=lambda n, rss: rss_mb.append(rss)
    )
    samples = settings.plan.n_samples * simulator.n_detectors
    queue.put((samples, seconds, rss_mb, peak_rss_mb(), clock.summary(samples)))


def measure(channel, days, nside, threads):
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=one_point, args=(channel, days, nside, threads, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def paper_grid_detector_samples(seeds: int = 100) -> float:
    """Detector-samples of the paper's grid: 22 channels x seeds x one year x 2 detectors."""
    from hwp_tes_systematics.instrument.channels import all_channel_names, load_channel

    per_seed = sum(
        load_channel(name).sampling_rate_hz * YEAR_DAYS * 86400.0 * 2
        for name in all_channel_names()
    )
    return per_seed * seeds


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, nargs="+", default=[1.0, 7.0, 30.0])
    parser.add_argument("--nsides", type=int, nargs="+", default=[64, 128, 256, 512])
    parser.add_argument("--threads", type=int, default=1)
    arguments = parser.parse_args()

    points = [(days, arguments.nsides[0]) for days in arguments.days]
    points += [(arguments.days[0], nside) for nside in arguments.nsides[1:]]
    print(f"{arguments.channel} pair, job path, {arguments.threads} thread(s), one-day chunks")
    print(
        "| duration | nside | detector-samples | wall time | ns per detector-sample "
        "| RSS after first / last chunk | peak RSS |"
    )
    print("|---|---|---|---|---|---|---|")
    ns_per_sample, stage_lines = {}, []
    for days, nside in points:
        samples, seconds, rss_mb, peak_mb, stages = measure(
            arguments.channel, days, nside, arguments.threads
        )
        ns_per_sample[nside] = 1e9 * seconds / samples
        print(
            f"| {days:g} d | {nside} | {samples:.2e} | {seconds:.1f} s "
            f"| {ns_per_sample[nside]:.0f} | {rss_mb[0]:.0f} / {rss_mb[-1]:.0f} MB "
            f"| {peak_mb:.0f} MB |",
            flush=True,
        )
        stage_lines.append(f"{days:g} d, nside {nside}: {stages}")
    print("\ntime per stage:\n" + "\n".join(stage_lines))
    grid_samples = paper_grid_detector_samples()
    largest = max(ns_per_sample)
    core_hours = grid_samples * ns_per_sample[largest] * 1e-9 / 3600
    year_pair_h = core_hours / 22 / 100
    print(
        f"\npaper grid: {grid_samples:.2e} detector-samples (22 channels x 100 seeds x 1 yr "
        f"x 2 detectors) at {ns_per_sample[largest]:.0f} ns (nside {largest}): "
        f"{core_hours:,.0f} core-hours (mean {year_pair_h:.2f} h per (channel, seed) job)"
    )


if __name__ == "__main__":
    main()
