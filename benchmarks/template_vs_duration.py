"""How the nonlinearity template averages down with the observing time, with and without
per-detector baselines: the groundwork of issue 13's "which terms of d^2 reach BB".

    python benchmarks/template_vs_duration.py --channel M1-140 --days 1 7 --nside 64
    python benchmarks/template_vs_duration.py --days 1 --hwp-rate-factors 1 1.00064

``--hwp-rate-factors`` scales the HWP rotation rate (and the notch with it): at the
nominal 39 rpm (MFT) the HWP turns exactly 780 times per 20-minute spin period (61 rpm,
HFT: 1220), so the leakage of successive spins can add coherently; a factor of
1.00064 (half a turn more per spin) breaks the commensurability.

For each duration, one pair of ``--channel`` is simulated through the job path (sky,
dipole, noise at the default config's noise_scale, the channel's A_2 from the default
optics), once with 60 s baselines and once on the paper-literal path, and the
template terms s^2, s h, h^2 of detector 0 are binned (:mod:`tod_maps`). Printed per
term: the Q/U rms per unit g1 over the observed pixels [K_CMB K] and the BB
pseudo-spectrum (observed pixels, / f_sky) averaged over ell 2-12, 12-40, 40-128
[K_CMB^2 K^2], and the correlation of the two detectors' total templates. Each point
runs in this process, one thread; a year of a pair takes ~15-25 min.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import healpy as hp
import numpy as np

from hwp_tes_systematics.channel_inputs import channel_a2_k_cmb, channel_sky
from hwp_tes_systematics.config import default_config_path, load_config
from hwp_tes_systematics.instrument import load_channel
from hwp_tes_systematics.mapmaking import solve_maps
from hwp_tes_systematics.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.tod_maps import (
    TEMPLATE_TERMS,
    PairMapSettings,
    accumulate,
    split_solved_maps,
)

ELL_BINS = ((2, 13), (13, 41), (41, 129))


def template_summary(terms, templates, good, nside):
    """Rows of (term, Q/U rms, BB per ell bin) for detector 0, and the detectors' correlation."""
    fsky = good.mean()
    rows = []
    labeled = [(name, terms[index, 0]) for index, name in enumerate(TEMPLATE_TERMS)]
    for name, maps in [*labeled, ("total", templates[0])]:
        masked = np.where(good, maps, 0.0)
        rms = float(np.sqrt(np.mean(maps[1:, good] ** 2)))
        bb = hp.anafast(masked, lmax=3 * nside - 1)[2] / fsky
        rows.append((name, rms, [float(bb[lo:hi].mean()) for lo, hi in ELL_BINS]))
    correlation = float(
        np.corrcoef(templates[0][1:, good].ravel(), templates[1][1:, good].ravel())[0, 1]
    )
    return rows, correlation


def one_point(config, channel_name, days, nside, baseline_length_s, hwp_rate_factor=1.0):
    channel = load_channel(channel_name)
    channel = dataclasses.replace(channel, hwp_rpm=channel.hwp_rpm * hwp_rate_factor)
    plan = MissionPlan(
        config["simulation"]["mission_start_tdb"], days * 86400.0, 86400.0, channel.sampling_rate_hz
    )
    a2_k = channel_a2_k_cmb(config, channel_name)
    settings = PairMapSettings(
        master_seed=config["master_seed"],
        seed=0,
        nside=nside,
        plan=plan,
        a2_k_cmb=a2_k,
        notch_width_divisor=config["notch"]["width_divisor"],
        notch_margin_s=config["notch"]["margin_s"],
        max_condition_number=config["maps"]["max_condition_number"],
        noise_scale=config["simulation"]["noise_scale"],
        baseline_length_s=baseline_length_s,
    )
    simulator = PairSimulator(channel, plan, nside)
    simulator.hwp_rad_per_s = channel.hwp_frequency_hz * 2 * np.pi  # the scaled rate
    sky = channel_sky({**config, "maps": {**config["maps"], "nside": nside}}, channel, 0)["total"]
    maps, _, good = solve_maps(accumulate(simulator, settings, sky), 100.0)
    solved = split_solved_maps(maps, simulator.n_detectors, a2_k)
    return template_summary(solved["template_terms"], solved["templates"], good, nside), good


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, nargs="+", default=[1.0])
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--hwp-rate-factors", type=float, nargs="+", default=[1.0])
    arguments = parser.parse_args()
    config = load_config(default_config_path())
    print(
        "| days | HWP rate x | baselines | term | Q/U rms per unit g1 [K K] | BB ell 2-12 | ell 13-40 | "
        "ell 41-128 [K^2 K^2] | observed | detector correlation | wall [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    points = [
        (days, factor, baselines)
        for days in arguments.days
        for factor in arguments.hwp_rate_factors
        for baselines in (60.0, None)
    ]
    for days, factor, baselines in points:
        started = time.perf_counter()
        (rows, correlation), good = one_point(
            config, arguments.channel, days, arguments.nside, baselines, factor
        )
        wall = time.perf_counter() - started
        for name, rms, bb in rows:
            print(
                f"| {days:g} | {factor:g} | {baselines or 'none'} | {name} | {rms:.3g} | "
                f"{bb[0]:.2g} | {bb[1]:.2g} | {bb[2]:.2g} | {good.mean():.0%} | "
                f"{correlation:+.4f} | {wall:.0f} |"
            )


if __name__ == "__main__":
    main()
