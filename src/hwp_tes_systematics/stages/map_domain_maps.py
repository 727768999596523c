"""Stages of the map-domain path (``simulation.realizations: map_domain``): the fixed TOD
pass of one channel, then the maps file of each seed from it (:mod:`map_domain`)."""

from __future__ import annotations

import logging
import time

import pandas as pd

from .. import config as cfg
from .. import map_domain, seeding, sky
from ..io import use_threads
from ..maps_file import maps_attributes, write_channel_maps
from ..tod import PairSimulator
from ..tod_maps import PairMapSettings

log = logging.getLogger(__name__)


def run_fixed_pass(
    config: dict, channel_name: str, kw_csv: str, foreground_fits: str, out_h5: str, threads=1
):
    """Simulate the seed-independent TOD of one channel once and write its fixed maps."""
    started = time.perf_counter()
    use_threads(threads)
    channel = cfg.channel(config, channel_name)
    carries_systematics = channel_name in config["instrument"]["systematics_channels"]
    kw = pd.read_csv(kw_csv).set_index("channel")
    a2_k_cmb = float(kw.loc[channel_name, "a2_k_cmb"]) if carries_systematics else 0.0
    settings = PairMapSettings.from_config(
        config, channel, map_domain.NOISE_REFERENCE_SEED, a2_k_cmb, threads
    )
    simulator = PairSimulator.from_config(config, channel, settings.plan, settings.nside, threads)
    foreground = sky.read_sky_map(foreground_fits, nside=settings.nside)
    lmax = 3 * settings.nside - 1
    transfer_alm = map_domain.transfer_cmb_alm(
        lmax, config["simulation"]["cmb_r"], config["master_seed"], channel.fwhm_arcmin
    )
    log.info(
        "%s fixed pass: A_2 = %.4g K_CMB, systematics %s, %d chunks",
        channel_name,
        a2_k_cmb,
        carries_systematics,
        len(settings.plan.chunks()),
    )
    fixed = map_domain.fixed_pass(
        simulator,
        settings,
        foreground,
        transfer_alm,
        carries_systematics,
        lmax,
        config["simulation"]["calibration_every_chunks"],
        measure_lmax=config["simulation"]["filter_lmax"],  # null: the full band
    )
    attributes = maps_attributes(settings, simulator, fixed.good.mean())
    attributes["foreground_source"] = sky.read_sky_header(foreground_fits).get(
        "FGSOURCE", "unknown"
    )
    del attributes["seed"]
    map_domain.write_fixed_maps(out_h5, fixed, attributes)
    log.info(
        "%s fixed pass: wrote %s in %.1f s (observed %.0f %%; CMB transfer T_BB at ell "
        "2-20, 20-60, 60-128: %.2f, %.2f, %.2f)",
        channel_name,
        out_h5,
        time.perf_counter() - started,
        100 * fixed.good.mean(),
        fixed.transfer[2, 2:20].mean(),
        fixed.transfer[2, 20:60].mean(),
        fixed.transfer[2, 60:129].mean(),
    )


def run_seeds(config: dict, channel_name: str, seeds, fixed_h5: str, out_h5s) -> None:
    """Write the maps file of each (channel, seed) from the channel's fixed pass: one job
    per channel (a seed costs ~1 s of map products at nside 64, less than starting a job)."""
    started = time.perf_counter()
    fixed, attributes = map_domain.read_fixed_maps(fixed_h5)
    channel = cfg.channel(config, channel_name)
    lmax = 3 * int(attributes["nside"]) - 1
    master_seed = config["master_seed"]
    detectors = list(attributes["detectors"])
    filter_lmax = config["simulation"]["filter_lmax"]
    if filter_lmax is not None and filter_lmax > lmax:
        raise ValueError(
            f"simulation.filter_lmax = {filter_lmax} exceeds the map's band 3 nside - 1 = {lmax}"
        )
    filter_lmax = lmax if filter_lmax is None else filter_lmax
    measured = fixed.transfer.shape[1] - 1
    if measured < filter_lmax:
        raise ValueError(
            f"{fixed_h5}: the fixed pass measured the filter up to ell = {measured}, but "
            f"simulation.filter_lmax asks for {filter_lmax}: rerun its fixed_pass rule"
        )
    operators = map_domain.SeedOperators(fixed, config["simulation"]["noise_scale"], filter_lmax)
    for seed, out_h5 in zip(seeds, out_h5s, strict=True):
        cmb_alm, cmb_band = map_domain.band_limited_seed_cmb(
            lmax, config["simulation"]["cmb_r"], master_seed, seed, channel.fwhm_arcmin
        )

        def rng_of_detector(k, seed=seed):
            return seeding.rng(master_seed, "map-domain noise", channel_name, seed, detectors[k])

        maps = map_domain.realize_seed(
            fixed,
            cmb_alm,
            cmb_band,
            float(attributes["a2_k_cmb"]),
            config["simulation"]["noise_scale"],
            rng_of_detector,
            operators,
        )
        seed_attributes = {**attributes, "seed": seed, "realization": "map_domain"}
        write_channel_maps(out_h5, maps, fixed.hits, fixed.condition, seed_attributes)
        log.info("%s seed %d: wrote %s", channel_name, seed, out_h5)
    log.info("%s: %d seeds in %.1f s", channel_name, len(out_h5s), time.perf_counter() - started)
