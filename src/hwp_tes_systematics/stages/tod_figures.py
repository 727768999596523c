"""Stage: a stretch of TOD with and without nonlinearity (paper Figs. 5, 6) and the notch."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from .. import config as cfg
from ..figures import tod as tod_figures
from ..instrument.nonlinearity import apply_nonlinearity
from ..simulation.channel_inputs import channel_sky
from ..simulation.tod import MissionPlan, PairSimulator

log = logging.getLogger(__name__)


def sample_tod(config: dict, channel_name: str, a2_k_cmb: float, hours: float):
    """(times [s], d [K_CMB] of the pair) over the first ``hours`` of the mission, seed 0."""
    channel = cfg.channel(config, channel_name)
    plan = MissionPlan(
        config["simulation"]["mission_start_tdb"],
        hours * 3600.0,
        hours * 3600.0,
        channel.sampling_rate_hz,
    )
    nside = config["maps"]["nside"]
    simulator = PairSimulator.from_config(config, channel, plan, nside)
    sky_maps = channel_sky(config, channel, 0)
    pointing = simulator.pointing(0, plan.n_samples)
    tod = (
        simulator.scan_sky(pointing, sky_maps["total"])
        + simulator.dipole(pointing)
        + simulator.hwpss(pointing, a2_k_cmb)
        + simulator.noise(
            pointing, config["master_seed"], 0, 0, config["simulation"]["noise_scale"]
        )
    )
    return np.arange(plan.n_samples) / plan.sampling_rate_hz, tod, channel


def run(config: dict, kw_csv: str, fig_chunk: str, fig_spectra: str, fig_notch: str) -> None:
    """Figs. 5 and 6 for figures.tod_channel, and the notch transfer function."""
    settings = config["figures"]
    name = settings["tod_channel"]
    kw = pd.read_csv(kw_csv).set_index("channel")
    times_s, tod, channel = sample_tod(
        config, name, float(kw.loc[name, "a2_k_cmb"]), settings["tod_sample_hours"]
    )
    g1_per_k = settings["tod_g1_per_k"]
    tod_nl = apply_nonlinearity(tod, g1_per_k)
    log.info("%s: %d samples simulated for the TOD figures", name, times_s.size)
    tod_figures.plot_tod_chunk(times_s, tod[0], tod_nl[0], g1_per_k, name, fig_chunk)
    spin_rate_hz = 0.05 / 60.0  # PTEP: spin 0.05 rpm; the dipole is modulated at this rate
    tod_figures.plot_tod_spectra(
        tod[0],
        tod_nl[0],
        channel.sampling_rate_hz,
        channel.hwp_frequency_hz,
        spin_rate_hz,
        g1_per_k,
        name,
        fig_spectra,
    )
    f_hwp = {
        telescope: cfg.channel(config, names[0]).hwp_frequency_hz
        for telescope, names in _first_channel_by_telescope(config).items()
    }
    tod_figures.plot_notch_transfer(f_hwp, config["notch"]["width_divisor"], fig_notch)
    log.info("wrote %s, %s, %s", fig_chunk, fig_spectra, fig_notch)


def _first_channel_by_telescope(config: dict) -> dict:
    from ..instrument.channels import channel_names_by_telescope

    by_telescope = channel_names_by_telescope(
        config["instrument"]["imo_location"], config["instrument"]["imo_release"]
    )
    return {telescope: names for telescope, names in by_telescope.items() if names}
