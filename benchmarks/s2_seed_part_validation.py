"""The demodulated seeds' s^2 piece against the full TOD path, on the pipeline's sky.

Demodulation keeps the s^2 term's 2 s_f x CMB (s_f: foreground + dipole), which the
map-domain seeds model as S^s (a shaping) of a pixel product (:func:`fixed_maps.static_sky_product`,
S^s measured in the fixed pass). tests/simulation/test_map_domain_demodulated.py checks it on one
day with a synthetic foreground; this script checks it where it will be used: the
pipeline's foreground map of a channel (a run's ``results/sky/foreground_<channel>.fits``),
its dipole, the paper's notch, no baselines, days to months of scanning.

    python benchmarks/s2_seed_part_validation.py \
        --foreground RUN/results/sky/foreground_M1-140.fits --days 30 --nside 64 --seeds 3

For each seed (noiseless: the piece does not depend on the noise), the seed's part of
the template (the template minus the fixed pass's, summed over the pair's detectors) on
both paths. Printed per multipole band, E and B power over the observed pixels at
|b| >= ``--galactic-cut-deg``: modelled over full path, the difference's power over the
full path's, the same with the piece left out, and the seed part's power over the whole
template's (how much the piece weighs). ``--out``: the same as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import healpy as hp
import numpy as np
from common import fixed_pass_setup

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose.testbed import nominal
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.simulation import fixed_maps, map_domain
from hwp_tes_systematics.simulation.demodulation import DemodulatedEquations
from hwp_tes_systematics.simulation.tod_maps import (
    accumulate,
    split_solved_maps,
    templates_from_terms,
)
from hwp_tes_systematics.sky import cmb as sky_cmb
from hwp_tes_systematics.sky.harmonics import BandLimitedSky

MASTER_SEED = 7


def band_powers(maps, observed, bands, lmax):
    """(n_bands, 2) E and B power of the maps (3, npix) on ``observed``, per band."""
    cl = hp.anafast(np.where(observed, maps, 0.0), lmax=lmax)[1:3]
    return np.array([cl[:, first:last].sum(axis=1) for first, last in bands])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--foreground", required=True, help="a run's foreground FITS map")
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=30.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--rate-hz", type=float, default=19.0, help="config/one_year.yaml's")
    parser.add_argument("--galactic-cut-deg", type=float, default=20.0)
    parser.add_argument("--out", type=Path, help="JSON of the printed numbers")
    args = parser.parse_args(argv)
    if not Path(args.foreground).is_file():
        parser.error(f"--foreground {args.foreground}: no such file (a run's results/sky/)")

    started = time.perf_counter()
    nside, lmax = args.nside, 3 * args.nside - 1
    channel = load_channel(args.channel)
    a2_k_cmb = nominal(args.channel)["a2_k"]
    # no baselines, as config/resolution_study_demodulated.yaml
    simulator, settings = fixed_pass_setup(
        args.channel, args.days, nside, args.rate_hz, a2_k_cmb, None, seed=MASTER_SEED
    )
    foreground = sky.read_sky_map(args.foreground)
    if hp.npix2nside(foreground.shape[-1]) != nside:  # band-limited to the map's band
        foreground = hp.alm2map(hp.map2alm(foreground, lmax=lmax), nside, lmax=lmax)
    fwhm = channel.fwhm_arcmin
    transfer_alm = sky_cmb.transfer_cmb_alm(lmax, 0.0, MASTER_SEED, fwhm)
    fixed = fixed_maps.fixed_pass(
        simulator, settings, foreground, transfer_alm, True, lmax, demodulated=True
    )
    print(f"fixed pass: {time.perf_counter() - started:.0f} s", flush=True)

    theta, _ = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    latitude = np.abs(90.0 - np.degrees(theta))
    observed = fixed.good & (latitude >= args.galactic_cut_deg)
    bands = [(2, 40), (40, 80), (80, 130), (130, lmax + 1)]
    bands = [(first, min(last, lmax + 1)) for first, last in bands if first <= lmax]
    fixed_templates = templates_from_terms(fixed.template_terms, a2_k_cmb)
    left_out_fixed = dataclasses.replace(fixed, cmb_s_shaping=np.zeros(0))
    scanned_foreground = BandLimitedSky.from_map(foreground, lmax)
    rows = []
    for seed in range(args.seeds):
        alm = sky_cmb.seed_cmb_alm(lmax, 0.0, MASTER_SEED, seed, fwhm)
        cmb = BandLimitedSky(alm, lmax)
        demodulated = DemodulatedEquations(nside, 1 + 3 * simulator.n_detectors + 2)
        accumulate(
            simulator,
            dataclasses.replace(settings, seed=seed, noise_scale=0.0),
            cmb + scanned_foreground,
            references_iqu_k=(cmb, scanned_foreground),
            demodulated=demodulated,
        )
        full = split_solved_maps(demodulated.solve(), simulator.n_detectors, a2_k_cmb)

        def seed_part(maps, fixed_maps=fixed_templates):
            return (maps["templates"] - fixed_maps).sum(axis=0)

        def fast(fixed_maps, seed=seed, alm=alm):
            return map_domain.realize_seed(
                fixed_maps, alm, lmax, a2_k_cmb, 0.0, lambda k: np.random.default_rng(k)
            )

        simulated = seed_part(full)
        modelled = seed_part(fast(fixed))
        left_out = seed_part(fast(left_out_fixed))
        scale = band_powers(simulated, observed, bands, lmax)
        whole = band_powers(full["templates"].sum(axis=0), observed, bands, lmax)
        rows.append(
            {
                "seed": seed,
                "modelled_over_full": band_powers(modelled, observed, bands, lmax) / scale,
                "difference_over_full": band_powers(modelled - simulated, observed, bands, lmax)
                / scale,
                "left_out_difference_over_full": band_powers(
                    left_out - simulated, observed, bands, lmax
                )
                / scale,
                "seed_part_over_whole": scale / whole,
            }
        )
        print(f"seed {seed}: {time.perf_counter() - started:.0f} s", flush=True)

    print(
        f"\n{args.channel}, {args.days:g} days, nside {nside}, {args.seeds} seeds, "
        f"|b| >= {args.galactic_cut_deg:g} deg (f_sky {observed.mean():.2f}); E/B power per "
        "band, mean over seeds (min-max)\n"
    )
    print("| quantity | " + " | ".join(f"ell {a}-{b - 1}" for a, b in bands) + " |")
    print("|---|" + "---|" * len(bands))
    summary = {}
    for name in rows[0]:
        if name == "seed":
            continue
        values = np.array([row[name] for row in rows])  # (seeds, bands, 2)
        summary[name] = values.tolist()
        for spectrum, label in enumerate(("EE", "BB")):
            cells = [
                f"{values[:, b, spectrum].mean():.3g} ({values[:, b, spectrum].min():.3g}-"
                f"{values[:, b, spectrum].max():.3g})"
                for b in range(len(bands))
            ]
            print(f"| {name} {label} | " + " | ".join(cells) + " |")
    print(f"\nwall time {time.perf_counter() - started:.0f} s")
    if args.out:
        args.out.write_text(
            json.dumps(
                {
                    "arguments": {k: str(v) for k, v in vars(args).items()},
                    "bands": bands,
                    "f_sky": float(observed.mean()),
                    "per_seed_bands_ee_bb": summary,
                    "wall_time_s": time.perf_counter() - started,
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
