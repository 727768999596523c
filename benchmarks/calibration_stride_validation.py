"""Is the filter's action measured as well on every n-th day as on all of them? The fixed
pass of the map-domain path (:func:`fixed_maps.fixed_pass`) with
``calibration_every_chunks`` = 1 and larger strides.

    python benchmarks/calibration_stride_validation.py --channels M1-140 H3-402 --days 16 \\
        --strides 4

For each channel and stride, printed against stride 1: the difference of the CMB
transfer T_EE and T_BB (it goes through 0 where the notch removes the CMB) and the ratio
of the noise shaping S_EE and S_BB, averaged over ell 2-20, 21-60 and 61-191; the Q/U rms ratio of the noise of a seed's nosys map and of the seed part of its
s h template term (4 seeds, the same random draws, so the ratio isolates the shaping);
the wall time of the pass. nside 64, 19 Hz, 60 s baselines, the default optics.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import config_fixed_pass

from hwp_tes_systematics.config import default_config_path, load_config
from hwp_tes_systematics.simulation import map_domain
from hwp_tes_systematics.sky import cmb as sky_cmb

NSIDE = 64
LMAX = 3 * NSIDE - 1
RATE_HZ = 19.0
ELL_BANDS = ((2, 21), (21, 61), (61, LMAX + 1))
SEEDS = range(4)


def fixed_pass(config, channel_name, days, every):
    """(FixedMaps, A_2 [K_CMB], CMB transfer a_lm's channel, wall seconds)."""
    return config_fixed_pass(
        config, channel_name, days, RATE_HZ, NSIDE, calibration_every_chunks=every
    )


def seed_noise(fixed, a2_k, channel, master_seed):
    """Q/U rms over seeds of the nosys map's noise and of the seed part of the s h term."""
    noise, sh = [], []
    good = fixed.good
    for seed in SEEDS:
        cmb_alm = sky_cmb.seed_cmb_alm(LMAX, 0.0, master_seed, seed, channel.fwhm_arcmin)
        maps = map_domain.realize_seed(
            fixed,
            cmb_alm,
            LMAX,
            a2_k,
            1.0,
            lambda k, seed=seed: np.random.default_rng([seed, k]),
        )
        noise.append(
            maps["nosys"][1:, good] - fixed.nosys[1:, good] - maps["cmb_reference"][1:, good]
        )
        sh.append(
            maps["template_terms"][map_domain.SH_TERM, 0][1:, good]
            - fixed.template_terms[map_domain.SH_TERM, 0][1:, good]
        )
    return float(np.sqrt(np.mean(np.square(noise)))), float(np.sqrt(np.mean(np.square(sh))))


def band_means(values):
    return [float(values[lo:hi].mean()) for lo, hi in ELL_BANDS]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", nargs="+", default=["M1-140", "H3-402"])
    parser.add_argument("--strides", type=int, nargs="+", default=[4])
    parser.add_argument("--days", type=float, default=16.0)
    arguments = parser.parse_args()
    config = load_config(default_config_path())
    bands = " / ".join(f"{lo}-{hi - 1}" for lo, hi in ELL_BANDS)
    print(
        f"| channel | stride | T_EE difference, ell {bands} | T_BB difference | S_EE ratio | "
        "S_BB ratio "
        "| seed noise rms ratio | seed s h rms ratio | wall [s] (stride 1) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for channel_name in arguments.channels:
        reference, a2_k, channel, reference_wall = fixed_pass(
            config, channel_name, arguments.days, 1
        )
        reference_noise = seed_noise(reference, a2_k, channel, config["master_seed"])
        for stride in arguments.strides:
            fixed, _, _, wall = fixed_pass(config, channel_name, arguments.days, stride)
            noise = seed_noise(fixed, a2_k, channel, config["master_seed"])
            cells = []
            for index in (1, 2):
                pairs = zip(
                    band_means(fixed.transfer[index]),
                    band_means(reference.transfer[index]),
                    strict=True,
                )
                cells.append(
                    " / ".join(f"{value - ref:+.3f} (of {ref:.2f})" for value, ref in pairs)
                )
            for index in (1, 2):
                ratios = np.divide(
                    band_means(fixed.noise_shaping[index]),
                    band_means(reference.noise_shaping[index]),
                )
                cells.append(" / ".join(f"{ratio:.3f}" for ratio in ratios))
            print(
                f"| {channel_name} | {stride} | {' | '.join(cells)} | "
                f"{noise[0] / reference_noise[0]:.3f} | {noise[1] / reference_noise[1]:.3f} | "
                f"{wall:.0f} ({reference_wall:.0f}) |",
                flush=True,
            )


if __name__ == "__main__":
    main()
