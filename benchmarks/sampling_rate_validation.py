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

import healpy as hp
import numpy as np
from common import config_fixed_pass

from hwp_tes_systematics.config import default_config_path, load_config
from hwp_tes_systematics.simulation.tod_maps import (
    TEMPLATE_TERMS,
    templates_from_terms,
)

NSIDE = 64
LMAX = 3 * NSIDE - 1


def fixed_pass(config, channel_name, rate_hz, days):
    """(FixedMaps, A_2 [K_CMB], wall seconds) of one pair at ``rate_hz``."""
    fixed, a2_k, _, seconds = config_fixed_pass(config, channel_name, days, rate_hz, NSIDE)
    return fixed, a2_k, seconds


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
