"""What power of the sky's BB does the filtered, binned map hold? Cross against auto
transfer on the TOD path.

The likelihood's transfer (``noise_model.csv`` ``sky_transfer_bb``) is the cross spectrum
of the recovered and the input CMB over the input's, T_ell. The map holds the auto
spectrum: for a filter that scales each mode by t, T = t and the map holds t^2 of the
power (the map-domain path emulates the filter so, :func:`filter_response.filtered_cmb_map`);
for a filter that keeps or removes modes whole, the map holds T. This script passes three
reference skies through one channel's TOD, paper filter (2f removal, notch, 60 s offsets)
and binning, no HWPSS, no noise (:func:`tod_maps.accumulate` references): the lensed CMB,
its E and T modes alone and its B modes alone, and prints per multipole band, on the
observed pixels (pseudo-spectra of the masked maps, input and output on the same mask):

- T_cross = C(out, in) / C(in) and T_auto = C(out) / C(in) of the B-only sky (B to B),
  beside T_cross^2 (the band's ratio squared) and the band's mean of T_ell^2 (per
  multipole, weighted by the input's power: what a filter that scales each mode by
  T_ell leaves; a band's T_cross^2 is below it where T_ell varies across the band);
- the leakage into B: the BB of the T-and-E-only sky's output over the lensing BB input
  (temperature and E modes the filter and the offsets turn into B);
- the full sky's T_cross and T_auto (what the noise model measures, and what the map holds).

    python benchmarks/cmb_power_transfer.py --channel M1-140 --days 365 --stride 15 --nside 64

``--sky-scanning band_limited`` scans the skies' a_lm at each sample's direction
(``simulation.sky_scanning``) instead of their maps at the nearest pixel.
"""

from __future__ import annotations

import argparse
import time

import healpy as hp
import numpy as np
from common import START_TDB, paper_settings

from hwp_tes_systematics import sky
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.io import reuse_freed_memory, use_threads
from hwp_tes_systematics.simulation.mapmaking import solve_maps
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import accumulate, split_solved_maps
from hwp_tes_systematics.sky.harmonics import BandLimitedSky

BANDS = ((2, 10), (11, 20), (21, 40), (41, 80), (81, 128))
MASTER_SEED = 20261129  # the reference CMB's draw; assumption


def reference_alms(fwhm_arcmin: float, lmax: int) -> dict[str, np.ndarray]:
    """a_lm (3, nalm) [K_CMB] of one lensed CMB (r = 0) at the beam: whole, with its B
    modes set to zero (T and E) and with only its B modes."""
    alm = sky.smooth_alm(sky.cmb_alm(lmax, 0.0, MASTER_SEED, 0), fwhm_arcmin, lmax)
    e_only, b_only = alm.copy(), np.zeros_like(alm)
    e_only[2] = 0.0
    b_only[2] = alm[2]
    return {"full": alm, "te_only": e_only, "b_only": b_only}


def reference_skies(nside: int, fwhm_arcmin: float, lmax: int) -> dict[str, np.ndarray]:
    """(3, npix) maps [K_CMB] of :func:`reference_alms`."""
    return {
        name: hp.alm2map(a, nside, lmax=lmax, pol=True)
        for name, a in reference_alms(fwhm_arcmin, lmax).items()
    }


def band(cl: np.ndarray, weight: np.ndarray, first: int, last: int) -> float:
    """The ``weight``-weighted mean of ``cl`` over first..last."""
    where = slice(first, last + 1)
    return float(np.sum(cl[where] * weight[where]) / np.sum(weight[where]))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=1.0)
    parser.add_argument("--stride", type=int, default=1, help="simulate one day in this many")
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument(
        "--sky-scanning", choices=("nearest_pixel", "band_limited"), default="nearest_pixel"
    )
    args = parser.parse_args(argv)
    use_threads(1)
    reuse_freed_memory()
    lmax = 2 * args.nside
    channel = load_channel(args.channel)
    plan = MissionPlan(
        START_TDB, args.days * 86400.0, 86400.0, channel.sampling_rate_hz, args.stride
    )
    settings = paper_settings(plan, args.nside, 0.0, baseline_length_s=60.0, noise_scale=0.0)
    simulator = PairSimulator(channel, plan, args.nside, noise_model="keshner")
    skies = reference_skies(args.nside, channel.fwhm_arcmin, 3 * args.nside - 1)
    scanned = list(skies.values())
    if args.sky_scanning == "band_limited":
        alms = reference_alms(channel.fwhm_arcmin, 3 * args.nside - 1)
        scanned = [BandLimitedSky(alm, 3 * args.nside - 1) for alm in alms.values()]
    started = time.perf_counter()
    equations = accumulate(
        simulator,
        settings,
        np.zeros((3, hp.nside2npix(args.nside))),
        references_iqu_k=scanned,
        template_terms=False,
    )
    maps, _, good = solve_maps(equations, settings.max_condition_number)
    outputs = dict(
        zip(skies, split_solved_maps(maps, simulator.n_detectors, 0.0, False)["references"])
    )
    print(
        f"{args.channel}, {args.days:g} days (one in {args.stride}), nside {args.nside}, "
        f"sky scanned {args.sky_scanning}, paper filter, 60 s offsets; observed "
        f"{good.mean():.1%}; "
        f"{time.perf_counter() - started:.0f} s"
    )

    def spectra(out, inp):
        masked_out, masked_in = (np.where(good, m, 0.0) for m in (out, inp))
        cross = hp.anafast(masked_out, masked_in, lmax=lmax)[2]
        return cross, hp.anafast(masked_out, lmax=lmax)[2], hp.anafast(masked_in, lmax=lmax)[2]

    b_cross, b_auto, b_in = spectra(outputs["b_only"], skies["b_only"])
    f_cross, f_auto, f_in = spectra(outputs["full"], skies["full"])
    _, e_leak, _ = spectra(outputs["te_only"], skies["te_only"])
    modes = 2 * np.arange(lmax + 1) + 1.0
    print(
        "ell band | B->B: T_cross, T_auto, T_cross^2, mean T_ell^2 | T,E->B leakage / C_BB | "
        "full: T_cross, T_auto"
    )
    t_ell = np.divide(b_cross, b_in, out=np.zeros_like(b_in), where=b_in > 0)
    for first, last in BANDS:
        if last > lmax:
            break
        t_cross = band(b_cross, modes, first, last) / band(b_in, modes, first, last)
        t_auto = band(b_auto, modes, first, last) / band(b_in, modes, first, last)
        leak = band(e_leak, modes, first, last) / band(b_in, modes, first, last)
        full_cross = band(f_cross, modes, first, last) / band(f_in, modes, first, last)
        full_auto = band(f_auto, modes, first, last) / band(f_in, modes, first, last)
        t_squared = band(t_ell**2, modes * b_in, first, last)
        print(
            f"  {first:3d}-{last:3d} | {t_cross:6.3f} {t_auto:6.3f} {t_cross**2:6.3f} "
            f"{t_squared:6.3f} | "
            f"{leak:6.3f} | {full_cross:6.3f} {full_auto:6.3f}"
        )


if __name__ == "__main__":
    main()
