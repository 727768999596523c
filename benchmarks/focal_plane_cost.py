"""What the full focal plane costs: detector-samples, fixed-pass core-hours and the memory
of one job, per channel, from the PTEP instrument model and the measured per-sample costs.

    python benchmarks/focal_plane_cost.py
    python benchmarks/focal_plane_cost.py --ns-per-detector-sample 731 --nside 512

An estimate from measured parts, not a run: the detector counts are litebird_sim's PTEP
model (``pairs_per_channel: all``), the sampling rates the configuration's
(``simulation.sampling_rate_hz`` for the systematics channels,
``sampling_rate_without_systematics_hz`` for the others: config/one_year.yaml), the cost
per detector-sample of a fixed pass the one measured by ``benchmarks/fixed_pass_profile.py``
(docs/fixed_pass_profile/: ~420 ns at nside 64 on one core of this machine; ~730 ns for
the nside-512 pass binned with and without offsets, measured in the nside-512 run), the
memory of a pass's chunks ``tod_maps.chunk_memory_bytes`` (measured on 1-4 pairs) and the
seeds' per-detector HWPSS moments ``mapmaking.PixelMoments`` (3 weights x 6 entries per
pixel and detector, float64). Printed per channel: detectors, detector-samples of a year,
fixed-pass core-hours, the memory of one fixed-pass job holding all the channel's
detectors in one-day chunks, the detectors a job of ``--job-memory-gb`` can hold, and the
seeds' moments for all the channel's detectors at ``--nside``.
"""

from __future__ import annotations

import argparse

YEAR_S = 365.25 * 86400.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ns-per-detector-sample", type=float, default=420.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--job-memory-gb", type=float, default=20.0)
    parser.add_argument("--configfile", default="config/one_year.yaml")
    arguments = parser.parse_args()

    from hwp_tes_systematics import config as cfg
    from hwp_tes_systematics.instrument.channels import load_channel
    from hwp_tes_systematics.simulation.mapmaking import MOMENT_WEIGHTS
    from hwp_tes_systematics.simulation.tod import MissionPlan
    from hwp_tes_systematics.simulation.tod_maps import (
        CHUNK_BYTES_PER_DETECTOR_SAMPLE,
        PASS_BASE_BYTES,
        PairMapSettings,
        chunk_memory_bytes,
    )

    config = cfg.load_config("config/config.yaml", arguments.configfile)
    npix = 12 * arguments.nside**2
    moment_bytes = len(MOMENT_WEIGHTS) * 6 * 8 * npix  # per detector
    print(
        f"full focal plane (PTEP, pairs_per_channel: all), one year, {arguments.configfile}'s "
        f"rates, {arguments.ns_per_detector_sample:g} ns per detector-sample, nside "
        f"{arguments.nside}, jobs of {arguments.job_memory_gb:g} GB"
    )
    print(
        "| channel | detectors | rate [Hz] | detector-samples | fixed pass [core-h] | "
        "one job, all detectors [GB] | detectors per job | seeds' moments [GB] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    totals = {"detectors": 0, "samples": 0.0, "core_h": 0.0}
    for name in cfg.selected_channels(config):
        channel = load_channel(name, None, "vPTEP", None, "all", None)
        rate = cfg.simulated_rate_hz(config, channel)
        n_det = len(channel.detectors)
        plan = MissionPlan("2032-04-01T00:00:00", 86400.0, 86400.0, rate)
        settings = PairMapSettings(
            master_seed=1,
            seed=0,
            nside=arguments.nside,
            plan=plan,
            a2_k_cmb=0.0,
            notch_width_divisor=100.0,
            notch_margin_s=config["notch"]["margin_s"],
            max_condition_number=100.0,
        )
        job_gb = chunk_memory_bytes(n_det, settings) / 1e9
        per_detector = (chunk_memory_bytes(1, settings) - PASS_BASE_BYTES) / 1e9
        fits = int((arguments.job_memory_gb - PASS_BASE_BYTES / 1e9) // per_detector)
        samples = n_det * rate * YEAR_S
        core_h = samples * arguments.ns_per_detector_sample * 1e-9 / 3600
        totals["detectors"] += n_det
        totals["samples"] += samples
        totals["core_h"] += core_h
        print(
            f"| {name} | {n_det} | {rate:g} | {samples:.3g} | {core_h:.0f} | {job_gb:.0f} | "
            f"{fits} | {n_det * moment_bytes / 1e9:.0f} |"
        )
    print(
        f"| **all** | {totals['detectors']} | | {totals['samples']:.3g} | "
        f"{totals['core_h']:.0f} | | | |"
    )
    print(
        f"memory model: {PASS_BASE_BYTES / 1e9:g} GB + {CHUNK_BYTES_PER_DETECTOR_SAMPLE} B per "
        "detector and sample of a chunk with its margins (tod_maps.chunk_memory_bytes)"
    )


if __name__ == "__main__":
    main()
