"""Benchmark of one (channel, seed) job: the linear-in-g1 path against a plain simulation.

    python benchmarks/pair_maps_benchmark.py --channel M1-140 --days 1 --nside 64

(a) plain: one simulation (sky + dipole + HWPSS + noise -> 2f removal -> notch -> binning)
    of one TOD, i.e. the cost of any single sigma_g1 case simulated directly;
(b) linear: the same plus the per-detector templates F(d_k^2), which give the maps of
    every sigma_g1 and every g1 draw;
(c) job: (b) plus the CMB and foreground reference TODs, what a pair_maps job runs.
Prints the time per stage, detector-samples per second, ns per detector-sample, the
resident memory after each chunk (it must stay flat as the duration grows) and the
cost ratio (b)/(a).
"""

from __future__ import annotations

import argparse

from common import pair_setup, peak_rss_mb, timed_accumulate, warm_up


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=1.0, help="mission duration [days]")
    parser.add_argument("--chunk-s", type=float, default=86400.0, help="chunk length [s]")
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--noise", default="keshner", help="noise model (keshner, toast)")
    parser.add_argument(
        "--only",
        choices=["plain", "linear", "job"],
        default=None,
        help="run one path only (e.g. for long memory runs)",
    )
    arguments = parser.parse_args()

    warm_up(arguments.channel, arguments.nside, arguments.threads, arguments.noise)
    simulator, settings, sky_map = pair_setup(
        arguments.channel,
        arguments.days * 86400.0,
        arguments.nside,
        arguments.threads,
        arguments.noise,
        arguments.chunk_s,
    )
    plan = settings.plan
    samples = plan.n_samples * simulator.n_detectors
    print(
        f"{arguments.channel}: {arguments.days:g} days, {samples:.3e} detector-samples, "
        f"nside {arguments.nside}, chunks of {arguments.chunk_s:g} s, "
        f"threads {arguments.threads}, noise {arguments.noise}"
    )
    seconds = {}
    for path in ("plain", "linear", "job"):
        if arguments.only not in (None, path):
            continue
        done = [0]

        def report(n_samples, rss_mb, path=path, done=done):
            done[0] += n_samples
            print(
                f"  {path:6s} after {done[0] / plan.sampling_rate_hz / 86400:7.2f} days: "
                f"RSS {rss_mb:7.0f} MB",
                flush=True,
            )

        _, seconds[path], clock = timed_accumulate(simulator, settings, sky_map, path, report)
        print(
            f"{path:6s}: {seconds[path]:8.1f} s, {samples / seconds[path]:.3e} "
            f"detector-samples/s, {1e9 * seconds[path] / samples:6.0f} ns per detector-sample"
        )
        print(f"        per stage: {clock.summary(samples)}")
    print(f"peak RSS of the process: {peak_rss_mb():.0f} MB")
    if "plain" in seconds and "linear" in seconds:
        print(
            f"cost ratio linear / plain = {seconds['linear'] / seconds['plain']:.2f} "
            "(target <= 1.3)"
        )
    print(
        f"one-year extrapolation ({plan.sampling_rate_hz:g} Hz, 2 detectors): "
        f"{max(seconds.values()) * 365.25 / arguments.days / 3600:.2f} h per (channel, seed)"
    )


if __name__ == "__main__":
    main()
