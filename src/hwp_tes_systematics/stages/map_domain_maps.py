"""Stages of the map-domain path (``simulation.realizations: map_domain``): the fixed TOD
pass of one channel, the analysis mask from all of them, then each seed's a_lm of the
channel (:mod:`map_domain`, :class:`channel_alms.ChannelAlms`)."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import pandas as pd

from .. import config as cfg
from .. import sky
from ..analysis import channel_alms
from ..io import reuse_freed_memory, use_threads
from ..simulation import fixed_maps, map_domain
from ..simulation.maps_file import maps_attributes
from ..simulation.tod import PairSimulator
from ..simulation.tod_maps import PairMapSettings
from ..sky import cmb as sky_cmb

log = logging.getLogger(__name__)


def run_fixed_pass(
    config: dict,
    channel_name: str,
    kw_csv: str,
    foreground_fits: str,
    out_h5s: dict[str, str],
    threads=1,
):
    """Simulate the seed-independent TOD of one channel once and write its fixed maps, one
    file per map-maker of the pass (``out_h5s``: {:func:`config.map_variant` name: path},
    every one of :func:`config.fixed_pass_variant_names`)."""
    started = time.perf_counter()
    use_threads(threads)
    reuse_freed_memory()  # the chunks' arrays: no page faults (io.reuse_freed_memory)
    channel = cfg.channel(config, channel_name)
    carries_systematics = channel_name in config["instrument"]["systematics_channels"]
    kw = pd.read_csv(kw_csv).set_index("channel")
    a2_k_cmb = float(kw.loc[channel_name, "a2_k_cmb"]) if carries_systematics else 0.0
    variants = cfg.fixed_pass_variants(config)
    names = cfg.fixed_pass_variant_names(config)
    if sorted(names) != sorted(out_h5s):
        raise ValueError(
            f"fixed pass of {channel_name}: outputs {sorted(out_h5s)}, variants {names}"
        )
    (scan_nside, primary_baseline), extra_variants = variants[0], variants[1:]
    settings = dataclasses.replace(
        PairMapSettings.from_config(
            config, channel, fixed_maps.NOISE_REFERENCE_SEED, a2_k_cmb, threads
        ),
        nside=scan_nside,
        baseline_length_s=primary_baseline,
    )
    simulator = PairSimulator.from_config(config, channel, settings.plan, scan_nside, threads)
    foreground = sky.read_sky_map(foreground_fits, nside=scan_nside)
    lmax = 3 * scan_nside - 1
    transfer_alm = sky_cmb.transfer_cmb_alm(
        lmax, config["simulation"]["cmb_r"], config["master_seed"], channel.fwhm_arcmin
    )
    log.info(
        "%s fixed pass: A_2 = %.4g K_CMB, systematics %s, %d chunks, map-makers %s",
        channel_name,
        a2_k_cmb,
        carries_systematics,
        len(settings.plan.chunks()),
        ", ".join(names),
    )
    passes = fixed_maps.fixed_passes(
        simulator,
        settings,
        foreground,
        transfer_alm,
        carries_systematics,
        lmax,
        config["simulation"]["calibration_every_chunks"],
        measure_lmax=config["simulation"]["filter_lmax"] or lmax,  # null: the full band
        extra_variants=extra_variants,
        noise_realizations=config["simulation"]["noise_reference_realizations"],
        demodulated_variants=cfg.demodulated_variants(config),
        band_limited_sky=config["simulation"]["sky_scanning"] == "band_limited",
    )
    source = sky.read_sky_header(foreground_fits).get("FGSOURCE", "unknown")
    for (nside, baseline, *demodulated), fixed in passes.items():
        name = cfg.map_variant(nside, baseline, bool(demodulated))
        variant_settings = dataclasses.replace(settings, nside=nside, baseline_length_s=baseline)
        attributes = maps_attributes(variant_settings, simulator, fixed.good.mean())
        attributes["foreground_source"] = source
        attributes["scan_nside"] = scan_nside
        attributes["noise_reference_realizations"] = config["simulation"][
            "noise_reference_realizations"
        ]
        attributes["map_maker"] = "demodulated" if demodulated else "binned"
        attributes["sky_scanning"] = config["simulation"]["sky_scanning"]
        attributes["cmb_r"] = config["simulation"]["cmb_r"]  # of the reference CMB
        del attributes["seed"]
        out_h5 = out_h5s[name]
        holder = Path(out_h5s[cfg.moments_variant(config, nside)]).name
        shared = None if holder == Path(out_h5).name else holder
        fixed_maps.write_fixed_maps(out_h5, fixed, attributes, moments_in=shared)
        log.info(
            "%s fixed pass %s: wrote %s (observed %.0f %%; CMB transfer T_BB at ell 2-20, "
            "20-60, 60-128: %.2f, %.2f, %.2f)",
            channel_name,
            name,
            out_h5,
            100 * fixed.good.mean(),
            fixed.transfer[2, 2:20].mean(),
            fixed.transfer[2, 20:60].mean(),
            fixed.transfer[2, 60:129].mean(),
        )
    log.info("%s fixed pass: %.1f s", channel_name, time.perf_counter() - started)


def run_mask(config: dict, fixed_h5s: list[str], out_h5: str) -> None:
    """The analysis mask from every channel's fixed pass (the pixels a seed observes are
    the fixed pass's ``good`` ones): what the seeds' a_lm are computed on."""
    observed = [fixed_maps.read_fixed_field(path, "good") for path in fixed_h5s]
    mask = channel_alms.analysis_mask(observed, config["component_separation"])
    channel_alms.write_mask(out_h5, mask, config["component_separation"])
    log.info(
        "analysis mask of %d channels: f_sky %.3f, wrote %s", len(observed), mask.mean(), out_h5
    )


def run_seeds(
    config: dict, channel_name: str, seeds, fixed_h5: str, mask_h5: str, out_h5s, pooled_h5s=()
) -> None:
    """Write each seed's a_lm of one channel (:class:`channel_alms.ChannelAlms`) from the
    channel's fixed pass: the seed's maps are made in memory
    (:class:`map_domain.ChannelSeeds`) and reduced to the a_lm the HILC combines, so no
    seed's maps reach the disk (at nside 512 they would take ~0.8 GB per channel and
    seed). One job per channel: the seeds share the fixed pass's operators.
    ``pooled_h5s``: the fixed passes whose noise shaping is pooled with this channel's
    (:func:`config.noise_shaping_siblings`)."""
    started = time.perf_counter()
    reuse_freed_memory()  # the seeds' maps and transforms: no page faults (io.reuse_freed_memory)
    channel_seeds = map_domain.ChannelSeeds(config, fixed_h5, pooled_h5s)
    if len(pooled_h5s) > 1:
        log.info("%s: noise shaping pooled over %d fixed passes", channel_name, len(pooled_h5s))
    mask = channel_alms.read_mask(mask_h5)
    if mask.size != channel_seeds.fixed.good.size:
        raise ValueError(
            f"{mask_h5}: {mask.size} pixels, but the fixed pass {fixed_h5} has "
            f"{channel_seeds.fixed.good.size}"
        )
    harmonic = channel_alms.HarmonicSettings.from_config(config)
    # what every seed shares, transformed once: the fixed pass's template terms (a seed
    # adds its pieces to the s h term) and, after the first seed, the foreground reference
    a2_k_cmb = float(channel_seeds.attributes["a2_k_cmb"])
    known = channel_alms.fixed_term_alms(
        config, channel_name, channel_seeds.fixed, a2_k_cmb, mask, harmonic
    )
    for seed, out_h5 in zip(seeds, out_h5s, strict=True):
        maps = channel_seeds.maps(seed, full_terms=False)
        alms = channel_alms.ChannelAlms.from_maps(
            config, seed, channel_name, maps, mask, harmonic, known
        )
        known["foreground_reference"] = alms.alms["foreground_reference"]
        channel_alms.write_channel_alms(
            out_h5, alms, channel_alms.alms_attributes(seed, harmonic, mask)
        )
        log.info("%s seed %d: wrote %s", channel_name, seed, out_h5)
    log.info("%s: %d seeds in %.1f s", channel_name, len(out_h5s), time.perf_counter() - started)
