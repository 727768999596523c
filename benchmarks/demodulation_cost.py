"""What the demodulating map-maker adds to a map-domain fixed pass, stage by stage.

    python benchmarks/demodulation_cost.py --days 1 --nsides 512 256 128 64

One fixed pass of M1-140 (the sky scanned at the first of ``--nsides``, every one binned
without baselines, as ``config/resolution_study_demodulated.yaml``), at 19 Hz, twice: the
binned map-makers alone, then with every one also demodulated and the sky scanned
band-limited (simulation.fixed_pass_demodulated, sky_scanning: band_limited). Printed:
each pass's time per stage per detector-sample (the clock :func:`tod_maps.accumulate`
keeps) and its wall time, whose difference beyond the per-sample sums is the
once-per-pass part (solving, the transfer and noise-shaping spectra of every variant).
Per-sample figures only compare within one run: on shared cores both rise.
"""

from __future__ import annotations

import argparse
import logging
import time

import healpy as hp
import numpy as np
from common import A2_K_CMB, fixed_pass_setup

from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.simulation import fixed_maps
from hwp_tes_systematics.sky import cmb as sky_cmb


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=float, default=1.0)
    parser.add_argument("--nsides", type=int, nargs="+", default=[512, 256, 128, 64])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--rate", type=float, default=19.0, help="sampling rate [Hz]")
    arguments = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("hwp_tes_systematics.simulation.map_domain").setLevel(logging.WARNING)
    channel = load_channel(arguments.channel)
    scan_nside = arguments.nsides[0]
    simulator, settings = fixed_pass_setup(
        arguments.channel, arguments.days, scan_nside, arguments.rate, A2_K_CMB, None
    )
    lmax = 3 * scan_nside - 1
    foreground = np.zeros((3, hp.nside2npix(scan_nside)))
    transfer_alm = sky_cmb.transfer_cmb_alm(lmax, 0.0, 1, channel.fwhm_arcmin)
    variants = [(nside, None) for nside in arguments.nsides]
    for demodulated in (False, True):
        started = time.perf_counter()
        fixed_maps.fixed_passes(
            simulator,
            settings,
            foreground,
            transfer_alm,
            True,
            lmax,
            measure_lmax=min(lmax, 2 * scan_nside),
            extra_variants=variants[1:],
            demodulated_variants=variants if demodulated else (),
            band_limited_sky=demodulated,
        )
        kind = "binned + demodulated, band-limited sky" if demodulated else "binned alone"
        print(f"{kind}: wall {time.perf_counter() - started:.0f} s", flush=True)


if __name__ == "__main__":
    main()
