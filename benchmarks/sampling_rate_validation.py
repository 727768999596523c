"""Does a lower TOD sampling rate give the same maps? The fixed pass of the map-domain path
(:func:`fixed_maps.fixed_pass`: noiseless maps, template terms, the filter's CMB transfer
and noise shaping) at the instrument model's rate and at lower ones.

    python benchmarks/sampling_rate_validation.py --channels M1-140 H3-402 --rates 15.5 19

For each channel and rate, printed against the instrument model's rate (31 Hz): for the
nosys map, each template term (s^2, s h, h^2, of detector 0) and the total template,
the relative Q/U rms difference (a map-level comparison) and the ratio of their BB
pseudo-spectra over ell 2-40 and 41-128 (what the likelihood sees), on the pixels
observed at both rates; the largest difference of the CMB transfer T_BB and of the noise
shaping S_BB over ell 2-128; the wall time of the pass. One day at nside 64 with 60 s
baselines and the default optics.
"""

from __future__ import annotations

import argparse
import time

import healpy as hp
import numpy as np

from hwp_tes_systematics.config import default_config_path, load_config
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.simulation import fixed_maps
from hwp_tes_systematics.simulation.channel_inputs import channel_a2_k_cmb, channel_sky
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import (
    TEMPLATE_TERMS,
    PairMapSettings,
    templates_from_terms,
)
from hwp_tes_systematics.sky import cmb as sky_cmb

NSIDE = 64
LMAX = 3 * NSIDE - 1


def fixed_pass(config, channel_name, rate_hz, days):
    channel = load_channel(channel_name)
    plan = MissionPlan(config["simulation"]["mission_start_tdb"], days * 86400.0, 86400.0, rate_hz)
    a2_k = channel_a2_k_cmb(config, channel_name)
    settings = PairMapSettings(
        master_seed=config["master_seed"],
        seed=fixed_maps.NOISE_REFERENCE_SEED,
        nside=NSIDE,
        plan=plan,
        a2_k_cmb=a2_k,
        notch_width_divisor=config["notch"]["width_divisor"],
        notch_margin_s=config["notch"]["margin_s"],
        max_condition_number=config["maps"]["max_condition_number"],
        baseline_length_s=config["maps"]["baseline_length_s"],
    )
    simulator = PairSimulator(channel, plan, NSIDE, noise_model="keshner")
    sky_config = {**config, "maps": {**config["maps"], "nside": NSIDE}}
    foreground = channel_sky(sky_config, channel, 0)["foreground"]
    transfer_alm = sky_cmb.transfer_cmb_alm(LMAX, 0.0, config["master_seed"], channel.fwhm_arcmin)
    started = time.perf_counter()
    fixed = fixed_maps.fixed_pass(simulator, settings, foreground, transfer_alm, True, LMAX)
    return fixed, a2_k, time.perf_counter() - started


def relative(a, b, good):
    return float(np.sqrt(np.mean((a - b)[1:, good] ** 2)) / np.sqrt(np.mean(b[1:, good] ** 2)))


def bb_ratios(a, b, good):
    """BB pseudo-spectrum ratio a / b over ell 2-40 and 41-128 (masked, same mask)."""
    bb_a, bb_b = (hp.anafast(np.where(good, m, 0.0), lmax=LMAX)[2] for m in (a, b))
    return [float(bb_a[lo:hi].sum() / bb_b[lo:hi].sum()) for lo, hi in ((2, 41), (41, 129))]


def compared(a, b, good):
    low, high = bb_ratios(a, b, good)
    return f"{relative(a, b, good):.2g} / {low:.2f} / {high:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", nargs="+", default=["M1-140", "H3-402"])
    parser.add_argument("--rates", type=float, nargs="+", default=[15.5, 19.0])
    parser.add_argument("--days", type=float, default=1.0)
    arguments = parser.parse_args()
    config = load_config(default_config_path())
    names = [*TEMPLATE_TERMS, "template"]
    print(
        "| channel | rate [Hz] | nosys: rms diff / BB ratio ell 2-40 / 41-128 | "
        + " | ".join(names)
        + " | max abs dT_BB | max abs dS_BB | wall [s] |"
    )
    print("|---|---|---|" + "---|" * len(names) + "---|---|---|")
    for channel_name in arguments.channels:
        reference, a2_k, wall = fixed_pass(config, channel_name, 31.0, arguments.days)
        rows = [(31.0, reference, wall)]
        for rate in arguments.rates:
            rows.append((rate, *fixed_pass(config, channel_name, rate, arguments.days)[::2]))
        for rate, fixed, wall in rows:
            good = fixed.good & reference.good
            terms = [
                compared(fixed.template_terms[j, 0], reference.template_terms[j, 0], good)
                for j in range(len(TEMPLATE_TERMS))
            ]
            total = compared(
                templates_from_terms(fixed.template_terms, a2_k)[0],
                templates_from_terms(reference.template_terms, a2_k)[0],
                good,
            )
            d_transfer = np.abs(fixed.transfer[2, 2:129] - reference.transfer[2, 2:129]).max()
            d_shaping = np.abs(
                fixed.noise_shaping[2, 2:129] - reference.noise_shaping[2, 2:129]
            ).max()
            print(
                f"| {channel_name} | {rate:g} | {compared(fixed.nosys, reference.nosys, good)} | "
                + " | ".join([*terms, total])
                + f" | {d_transfer:.3f} | {d_shaping:.3f} | {wall:.1f} |"
            )


if __name__ == "__main__":
    main()
