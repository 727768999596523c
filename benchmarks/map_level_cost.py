"""What the map-level stages cost per realization: the HILC of every case (nosys and each
sigma_g1 of the grid) and the systematic-only spectra, on synthetic maps of every channel.

    OMP_NUM_THREADS=1 python benchmarks/map_level_cost.py --nside 64
    OMP_NUM_THREADS=1 python benchmarks/map_level_cost.py --nside 512 --lmax 512 \
        --map2alm-iter 0 --seeds 100 --channels L1-040 L2-050 M1-140 H3-402   # paper grid

Writes maps files of all channels of the embedded default configuration (a common
CMB-like sky, white noise per channel, random template terms on the systematics
channels, none on the others; full sky with the default Galactic cut) and times (one thread with ``OMP_NUM_THREADS=1``, as a workflow job) what the
workflow's per-seed job does: ``component_separation`` (load, the a_lm of the no-systematics
maps, of the contamination sum_k z_k T_k and of the two references, computed once; the
weights and residual of every case; then the systematic-only spectra: the three template
terms of every systematics channel through the no-systematics weights, on the maps
already loaded). Prints seconds per seed
and the extrapolation to ``--seeds`` seeds in core-hours. The fixed TOD passes and the
seeds' maps are measured by ``benchmarks/map_domain_cost.py``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import healpy as hp
import numpy as np

from hwp_tes_systematics import config as cfg
from hwp_tes_systematics.analysis.ilc_residuals import SeedMaps
from hwp_tes_systematics.analysis.systematics import case_names
from hwp_tes_systematics.config import deep_merge, load_config
from hwp_tes_systematics.simulation.maps_file import write_channel_maps
from hwp_tes_systematics.simulation.tod_maps import templates_from_terms


def synthetic_maps(config: dict, folder: Path) -> dict[str, str]:
    """Maps files of every channel of ``config`` [K_CMB]; {channel: path}."""
    nside = config["maps"]["nside"]
    npix = hp.nside2npix(nside)
    rng = np.random.default_rng(1)
    cmb = rng.normal(size=(3, npix)) * 1e-6
    systematics = set(config["instrument"]["systematics_channels"])
    paths = {}
    for name in cfg.selected_channels(config):
        a2_k = 0.26 if name in systematics else 0.0
        n_det = 2 if name in systematics else 0  # as the workflow's files: no terms without
        terms = (
            rng.normal(size=(3, n_det, 3, npix)) * np.array([1e-6, 1e-4, 1e-3])[:, None, None, None]
        )
        maps = {
            "nosys": cmb + rng.normal(size=(3, npix)) * 1e-6,
            "template_terms": terms,
            "templates": templates_from_terms(terms, a2_k),
            "cmb_reference": cmb,
            "foreground_reference": np.zeros((3, npix)),
        }
        paths[name] = str(folder / f"{name}.h5")
        attributes = {"detectors": ["a", "b"], "a2_k_cmb": a2_k}
        write_channel_maps(paths[name], maps, np.ones(npix), np.ones(npix), attributes)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument(
        "--lmax", type=int, default=None, help="component_separation lmax (default: 2 nside)"
    )
    parser.add_argument(
        "--map2alm-iter", type=int, default=3, help="component_separation map2alm_iter"
    )
    parser.add_argument(
        "--channels",
        nargs="+",
        default="all",
        help="a subset of the channels (an nside-512 seed of all 22 needs ~24 GB): the cost "
        "is a sum over channels, so a subset with and without systematics gives each kind's",
    )
    arguments = parser.parse_args()
    config = deep_merge(
        load_config(cfg.default_config_path()),
        {
            "maps": {"nside": arguments.nside},
            "component_separation": {
                "lmax": arguments.lmax,
                "map2alm_iter": arguments.map2alm_iter,
            },
            "instrument": {"channels": arguments.channels},
        },
    )
    cases = case_names(config["requirement"]["sigma_g1_per_k"])
    with tempfile.TemporaryDirectory() as folder:
        paths = synthetic_maps(config, Path(folder))
        started = time.perf_counter()
        seed_maps = SeedMaps.load(config, 0, paths)
        load_s = time.perf_counter() - started
        started = time.perf_counter()
        nosys_weights = None
        for case in cases:
            result = seed_maps.residual(0.0 if case == cases[0] else 1e-3)
            nosys_weights = result["weights"] if nosys_weights is None else nosys_weights
        hilc_s = time.perf_counter() - started
        started = time.perf_counter()
        seed_maps.systematic_spectra(nosys_weights)
        systematic_s = time.perf_counter() - started
    per_seed = load_s + hilc_s + systematic_s
    print(
        f"nside {arguments.nside}, lmax {seed_maps.lmax}, {len(paths)} channels, "
        f"{len(cases)} cases, map2alm iter {arguments.map2alm_iter}, one thread"
    )
    print("| load + mask [s] | HILC of every case [s] | systematic spectra [s] | per seed [s] |")
    print("|---|---|---|---|")
    print(f"| {load_s:.1f} | {hilc_s:.1f} | {systematic_s:.1f} | {per_seed:.1f} |")
    core_h = arguments.seeds * per_seed / 3600
    print(
        f"{arguments.seeds} seeds: {core_h:.2f} core-hours, "
        f"{core_h / arguments.cores:.2f} h on {arguments.cores} cores"
    )


if __name__ == "__main__":
    main()
