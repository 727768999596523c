"""Benchmark of one (channel, seed) job: the linear-in-g1 path against a plain simulation.

    python benchmarks/pair_maps_benchmark.py --channel M1-140 --days 1 --nside 64

(a) plain: one simulation (sky + dipole + HWPSS + noise -> 2f removal -> notch -> binning)
    of one TOD, i.e. the cost of any single sigma_g1 case simulated directly;
(b) linear: the workflow's path, the same plus the per-detector templates F(d_k^2), which
    give the maps of every sigma_g1 and every g1 draw.
Prints detector-samples per second, ns per detector-sample, the resident memory after
each chunk (it must stay flat as the duration grows) and the cost ratio (b)/(a).
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from hwp_tes_systematics import sky
from hwp_tes_systematics.instrument import load_channel
from hwp_tes_systematics.stages.pair_maps import PairMapSettings, accumulate
from hwp_tes_systematics.tod import MissionPlan, PairSimulator


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=1.0, help="mission duration [days]")
    parser.add_argument("--chunk-s", type=float, default=86400.0, help="chunk length [s]")
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument(
        "--only",
        choices=["plain", "linear"],
        default=None,
        help="run one path only (e.g. for long memory runs)",
    )
    arguments = parser.parse_args()

    channel = load_channel(arguments.channel)
    plan = MissionPlan(
        "2032-04-01T00:00:00", arguments.days * 86400.0, arguments.chunk_s, channel.sampling_rate_hz
    )
    settings = PairMapSettings(
        master_seed=1,
        seed=0,
        nside=arguments.nside,
        plan=plan,
        a2_k_cmb=0.26,
        notch_width_divisor=100.0,
        notch_margin_s=1200.0,
        max_condition_number=100.0,
    )
    simulator = PairSimulator(channel, plan, arguments.nside)
    sky_map = sky.cmb_map(arguments.nside, 3 * arguments.nside - 1, 0.0, 1, 0, channel.fwhm_arcmin)
    warm = PairSimulator(
        channel,
        MissionPlan(plan.start_time_tdb, 600.0, 600.0, channel.sampling_rate_hz),
        arguments.nside,
    )
    accumulate(warm, PairMapSettings(**{**settings.__dict__, "plan": warm.plan}), sky_map)

    samples = plan.n_samples * simulator.n_detectors
    print(
        f"{arguments.channel}: {arguments.days:g} days, {samples:.3e} detector-samples, "
        f"nside {arguments.nside}, chunks of {arguments.chunk_s:g} s"
    )
    seconds = {}
    for path in ("plain", "linear"):
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

        started = time.perf_counter()
        g1 = np.zeros(simulator.n_detectors) if path == "plain" else None
        accumulate(simulator, settings, sky_map, g1_per_k=g1, on_chunk=report)
        seconds[path] = time.perf_counter() - started
        print(
            f"{path:6s}: {seconds[path]:8.1f} s, {samples / seconds[path]:.3e} "
            f"detector-samples/s, {1e9 * seconds[path] / samples:6.0f} ns per detector-sample"
        )
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS of the process: {peak_mb:.0f} MB")
    if len(seconds) == 2:
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
