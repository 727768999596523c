"""What a one-year run costs on the map-domain path: the fixed TOD pass per channel-day and
the map products per seed, measured, then extrapolated to a configuration's grid.

    python benchmarks/map_domain_cost.py --nside 64 --rate 19 --seeds 20 --days 4 \
        --calibration-every 4
    python benchmarks/map_domain_cost.py --nside 512 --rate 31 --seeds 100   # paper grid
    python benchmarks/map_domain_cost.py --seeds-only --nside 512 --filter-lmax 512
    python benchmarks/map_domain_cost.py --nside 512 --demodulated --band-limited

For one MFT channel with systematics (M1-140: 7 filtered TODs, HWPSS moments) and one
LFT channel without (L1-040: 4 TODs), one thread each, kernels compiled first: the fixed
pass of ``--days`` and of twice that (the difference is the cost per day, the rest the
once-per-pass part: solving the maps, the transfer and noise-shaping spectra), and the
realization of one seed (CMB draw, noise draw, map products). ``--calibration-every``:
the filter's transfer and noise shaping from every n-th day (``--days`` a multiple of it). Printed: seconds per channel-day and per
seed, and the extrapolation to 10 systematics + 12 other channels, one year and
``--seeds`` seeds, in core-hours and in wall hours on ``--cores`` cores. The map-level
stages after the maps (HILC, spectra, likelihood) are not included: they are measured
per job by the workflow (``results/benchmarks/``).
"""

from __future__ import annotations

import argparse
import resource
import time

import healpy as hp
import numpy as np
from common import run_fixed_pass

from hwp_tes_systematics.analysis.channel_alms import (
    ChannelAlms,
    HarmonicSettings,
    fixed_term_alms,
)
from hwp_tes_systematics.config import deep_merge, default_config_path, load_config
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.io import reuse_freed_memory
from hwp_tes_systematics.simulation import fixed_maps, map_domain
from hwp_tes_systematics.simulation.mapmaking import MATRIX_ENTRIES
from hwp_tes_systematics.sky import cmb as sky_cmb

CHANNELS = {"M1-140": (True, 10), "L1-040": (False, 12)}  # (systematics, channels like it)
YEAR_DAYS = 365.25


def measure(name, carries_systematics, nside, rate_hz, days, *pass_options):
    """(seconds of the fixed pass of ``days``, seconds per seed): the pass of
    :func:`common.run_fixed_pass`, ``pass_options`` its further arguments in order
    (calibration_every, measure_lmax, extra_variants, demodulated, band_limited), then
    one seed made from its map-maker at (``nside``, 60 s)."""
    fixed_s, passes, _ = run_fixed_pass(
        name, carries_systematics, nside, rate_hz, days, *pass_options
    )
    fixed = passes[(nside, 60.0)]
    lmax = 3 * nside - 1
    channel = load_channel(name)
    started = time.perf_counter()
    cmb_alm, band = sky_cmb.band_limited_seed_cmb(lmax, 0.0, 1, 0, channel.fwhm_arcmin)
    map_domain.realize_seed(fixed, cmb_alm, band, 0.264, 1.0, np.random.default_rng)
    return fixed_s, time.perf_counter() - started


def synthetic_full_sky(nside: int, carries_systematics: bool, samples_per_pixel: int = 8):
    """A FixedMaps of a year: every pixel good, its HWPSS moments summed over
    ``samples_per_pixel`` random HWP angles per detector (a^T a, h a^T a, h^2 a^T a with
    a = (1, cos 4 psi, sin 4 psi), h = cos 2 chi), flat transfer and noise shaping."""
    npix = hp.nside2npix(nside)
    lmax = 3 * nside - 1
    rng = np.random.default_rng(0)
    n_det = 2 if carries_systematics else 0
    moments = np.zeros((max(n_det, 1), npix, 3, 6))
    for k in range(max(n_det, 1)):
        for _ in range(samples_per_pixel):
            chi = rng.uniform(0, 2 * np.pi, npix)
            a = np.stack([np.ones(npix), np.cos(4 * chi), np.sin(4 * chi)])
            h = np.cos(2 * chi)
            for entry, (i, j) in enumerate(MATRIX_ENTRIES):
                for weight in range(3):
                    moments[k, :, weight, entry] += h**weight * a[i] * a[j]
    zeros = np.zeros((3, npix))
    return fixed_maps.FixedMaps(
        nosys=zeros,
        template_terms=np.zeros((3, n_det, 3, npix)),
        foreground_reference=zeros,
        transfer=np.ones((3, lmax + 1)),
        noise_shaping=np.full((3, lmax + 1), 0.9),
        noise_h_shaping=np.full((3, lmax + 1), 0.4),
        matrix=moments[:, :, 0].sum(axis=0).T.copy(),
        moments=moments if carries_systematics else np.zeros((0,)),
        hits=np.full(npix, 100.0),
        condition=np.full(npix, 2.0),
        good=np.ones(npix, bool),
        carries_systematics=carries_systematics,
    )


def seed_costs(
    nside: int, filter_lmax: int | None, seeds: int = 2, analysis_lmax=None, map2alm_iter=3
) -> None:
    """Prints what the ``map_domain_maps`` job of a one-year channel costs at ``nside``:
    the shared operators (noise factors, M^-1, H_k, the fixed template terms' a_lm: once
    per channel) and each seed (CMB
    draw to the beam's band limit and map products, the noise shaped up to
    ``filter_lmax``), as the workflow's ``map_domain_maps`` does, on a synthetic
    full-sky fixed pass."""
    lmax = 3 * nside - 1
    filter_lmax = lmax if filter_lmax is None else filter_lmax
    analysis_lmax = analysis_lmax or 2 * nside
    config = deep_merge(
        load_config(default_config_path()),
        {
            "maps": {"nside": nside},
            "component_separation": {"lmax": analysis_lmax, "map2alm_iter": map2alm_iter},
            "likelihood": {"lmax": min(128, analysis_lmax)},
        },
    )
    harmonic = HarmonicSettings.from_config(config)
    mask = np.ones(hp.nside2npix(nside))
    print(
        f"nside {nside}, lmax {lmax}, noise shaped to ell {filter_lmax}, full sky, one thread; "
        f"a_lm to {analysis_lmax} with {map2alm_iter} Jacobi iterations"
    )
    print(
        "| channel kind | shared operators, once per channel [s] | one seed [s] | of which its "
        "a_lm (map_domain_alms) [s] |"
    )
    print("|---|---|---|---|")
    for name, (carries, _) in CHANNELS.items():
        fixed = synthetic_full_sky(nside, carries)
        fwhm = load_channel(name).fwhm_arcmin
        started = time.perf_counter()
        operators = map_domain.SeedOperators(fixed, 1.0, filter_lmax)
        # as the map_domain_alms job: the fixed pass's term a_lm once, each seed without
        # its full terms (the foreground reference's a_lm, once too, left out here)
        known = fixed_term_alms(config, name, fixed, 0.264, mask, harmonic)
        factors_s = time.perf_counter() - started
        started = time.perf_counter()
        reduce_s = 0.0
        for seed in range(seeds):
            cmb_alm, band = sky_cmb.band_limited_seed_cmb(lmax, 0.0, 1, seed, fwhm)
            maps = map_domain.realize_seed(
                fixed, cmb_alm, band, 0.264, 1.0, np.random.default_rng, operators, False
            )
            reduced = time.perf_counter()
            maps["attrs"] = {"detectors": ["a", "b"][: 2 if carries else 1], "a2_k_cmb": 0.264}
            ChannelAlms.from_maps(config, seed, name, maps, mask, harmonic, known)
            reduce_s += time.perf_counter() - reduced
        per_seed = (time.perf_counter() - started) / seeds
        kind = "with systematics" if carries else "without"
        print(f"| {name} ({kind}) | {factors_s:.1f} | {per_seed:.1f} | {reduce_s / seeds:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--rate", type=float, default=19.0, help="sampling rate [Hz]")
    parser.add_argument("--days", type=float, default=1.0)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--calibration-every", type=int, default=1, help="days")
    parser.add_argument(
        "--seeds-only",
        action="store_true",
        help="time only the seeds' map products, on a synthetic full-sky fixed pass",
    )
    parser.add_argument(
        "--filter-lmax",
        type=int,
        default=None,
        help="simulation.filter_lmax: the seeds' filter band and, without --seeds-only, the "
        "band to which the fixed pass measures T_ell and S_ell (default: 3 nside - 1)",
    )
    parser.add_argument(
        "--analysis-lmax", type=int, help="component_separation.lmax (default 2 nside)"
    )
    parser.add_argument("--map2alm-iter", type=int, default=3, help="component_separation")
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="glibc's defaults instead of io.reuse_freed_memory (which the jobs call)",
    )
    parser.add_argument(
        "--also-nsides",
        type=int,
        nargs="*",
        default=[],
        help="further resolutions binned in the same pass (simulation.fixed_pass_nsides)",
    )
    parser.add_argument(
        "--also-without-baselines",
        action="store_true",
        help="also bin without baselines in the same pass (fixed_pass_baseline_lengths_s)",
    )
    parser.add_argument(
        "--demodulated",
        action="store_true",
        help="also bin every map-maker demodulated (simulation.fixed_pass_demodulated)",
    )
    parser.add_argument(
        "--band-limited",
        action="store_true",
        help="scan the sky from its a_lm (simulation.sky_scanning: band_limited)",
    )
    arguments = parser.parse_args()
    if not arguments.default_malloc:
        reuse_freed_memory()
    baselines = [60.0, None] if arguments.also_without_baselines else [60.0]
    extra = [(n, b) for n in [arguments.nside, *arguments.also_nsides] for b in baselines]
    extra = [variant for variant in extra if variant != (arguments.nside, 60.0)]
    if arguments.seeds_only:
        seed_costs(
            arguments.nside,
            arguments.filter_lmax,
            analysis_lmax=arguments.analysis_lmax,
            map2alm_iter=arguments.map2alm_iter,
        )
        return
    for name, (carries, _) in CHANNELS.items():  # compile the kernels of both kinds
        measure(name, carries, arguments.nside, arguments.rate, 0.05, 1, arguments.filter_lmax)
    total_core_s = 0.0
    print(
        f"nside {arguments.nside}, {arguments.rate:g} Hz, {arguments.seeds} seeds, one year, "
        f"calibration every {arguments.calibration_every} days, further map-makers {extra}, "
        f"demodulated {arguments.demodulated}, band-limited sky {arguments.band_limited}"
    )
    print(
        "| channel | fixed pass [s per day] | once per pass [s] | one year [min] | one seed [s] "
        "| x channels |"
    )
    print("|---|---|---|---|---|---|")
    for name, (carries, count) in CHANNELS.items():
        # two durations: the slope is the cost per day, the intercept the once-per-pass part
        # (solving the maps, the transfer and noise-shaping spectra)
        point = (name, carries, arguments.nside, arguments.rate)
        settings = (arguments.calibration_every, arguments.filter_lmax, extra)
        settings += (arguments.demodulated, arguments.band_limited)
        short_s, per_seed = measure(*point, arguments.days, *settings)
        long_s, _ = measure(*point, 2 * arguments.days, *settings)
        per_day = (long_s - short_s) / arguments.days
        once_s = short_s - per_day * arguments.days
        year_s = per_day * YEAR_DAYS + once_s
        total_core_s += count * (year_s + arguments.seeds * per_seed)
        print(
            f"| {name} | {per_day:.2f} | {once_s:.1f} | {year_s / 60:.1f} | {per_seed:.2f} | "
            f"{count} |"
        )
    print(
        f"fixed passes + seeds: {total_core_s / 3600:.2f} core-hours, "
        f"{total_core_s / 3600 / arguments.cores:.2f} h on {arguments.cores} cores; "
        f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.1f} GiB "
        "(the process, its largest pass)"
    )


if __name__ == "__main__":
    main()
