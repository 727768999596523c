"""Stage: TOD -> 4f notch -> baselines -> binned maps for one (channel, seed), linear in g1.

The simulation, filtering and accumulation are :func:`tod_maps.accumulate` (see that
module for the linear decomposition m(g1) = m_nosys + sum_k g1_k T_k and the three
template terms); this stage reads the sky, runs it and writes the maps file. One
simulation gives m_nosys and the per-detector templates: the sigma_g1 grid is a
parameter of the later stages, not of the simulation.
"""

from __future__ import annotations

import logging
import time

from .. import config as cfg
from .. import sky
from ..io import reuse_freed_memory, use_threads
from ..simulation.mapmaking import NormalEquations, solve_maps
from ..simulation.maps_file import maps_attributes, write_channel_maps
from ..simulation.tod import PairSimulator
from ..simulation.tod_maps import PairMapSettings, accumulate, split_solved_maps
from ..sky.cmb import seed_cmb_alm
from ..sky.harmonics import BandLimitedSky

log = logging.getLogger(__name__)


def write_pair_maps(path, equations: NormalEquations, settings, simulator, metadata: dict) -> None:
    """Solve the normal equations and write the maps file (:mod:`maps_file`)."""
    maps, condition, good = solve_maps(equations, settings.max_condition_number)
    solved = split_solved_maps(maps, simulator.n_detectors, settings.a2_k_cmb)
    solved["cmb_reference"], solved["foreground_reference"] = solved["references"]
    attributes = maps_attributes(settings, simulator, good.mean())
    write_channel_maps(path, solved, equations.hits, condition, {**attributes, **metadata})


def run(
    config: dict,
    channel_name: str,
    seed: int,
    kw_csv: str,
    foreground_fits: str,
    out_h5: str,
    threads: int = 1,
):
    """Simulate one (channel, seed) and write its maps and templates."""
    import pandas as pd

    started = time.perf_counter()
    use_threads(threads)
    reuse_freed_memory()  # the chunks' arrays: no page faults (io.reuse_freed_memory)
    channel = cfg.channel(config, channel_name)
    kw = pd.read_csv(kw_csv).set_index("channel")
    carries_systematics = channel_name in config["instrument"]["systematics_channels"]
    a2_k_cmb = float(kw.loc[channel_name, "a2_k_cmb"]) if carries_systematics else 0.0
    settings = PairMapSettings.from_config(config, channel, seed, a2_k_cmb, threads)
    simulator = PairSimulator.from_config(config, channel, settings.plan, settings.nside, threads)
    foreground = sky.read_sky_map(foreground_fits, nside=settings.nside)
    foreground_source = sky.read_sky_header(foreground_fits).get("FGSOURCE", "unknown")
    lmax = 3 * settings.nside - 1
    cmb_draw = (lmax, config["simulation"]["cmb_r"], config["master_seed"], seed)
    if config["simulation"]["sky_scanning"] == "band_limited":  # the same draw, as a_lm
        cmb = BandLimitedSky(seed_cmb_alm(*cmb_draw, channel.fwhm_arcmin), lmax, threads)
        foreground = BandLimitedSky.from_map(foreground, lmax, threads)
    else:
        cmb = sky.cmb_map(settings.nside, *cmb_draw, channel.fwhm_arcmin)
    log.info(
        "%s seed %d: sky ready (foreground: %s); A_2 = %.4g K_CMB; %d chunks",
        channel_name,
        seed,
        foreground_source,
        a2_k_cmb,
        len(settings.plan.chunks()),
    )
    equations = accumulate(
        simulator, settings, cmb + foreground, references_iqu_k=(cmb, foreground)
    )
    write_pair_maps(
        out_h5, equations, settings, simulator, {"foreground_source": foreground_source}
    )
    elapsed_s = time.perf_counter() - started
    samples = settings.plan.simulated_samples * simulator.n_detectors
    log.info(
        "%s seed %d: wrote %s in %.1f s (%.0f ns per detector-sample, start-up included)",
        channel_name,
        seed,
        out_h5,
        elapsed_s,
        1e9 * elapsed_s / samples,
    )
