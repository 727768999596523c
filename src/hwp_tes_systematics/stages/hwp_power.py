"""Stage: HWP power tables (per channel, per axis) and the paper's Figs. 1-3."""

from __future__ import annotations

import logging

import pandas as pd

from .. import config as cfg
from ..figures import hwp as hwp_figures
from ..instrument.hwp_power import hwp_power_for_channel
from ..io import write_csv

log = logging.getLogger(__name__)


def hwp_power_table(config: dict) -> pd.DataFrame:
    """One row per configured channel: HWP emission and transmitted load per axis, A_2 [W]."""
    rows = []
    for name in cfg.selected_channels(config):
        channel = cfg.channel(config, name)
        curves, elements, hwp_temperature_k = cfg.telescope_optics(config, channel.telescope)
        rows.append(
            hwp_power_for_channel(
                channel,
                curves,
                hwp_temperature_k,
                elements,
                incoming_load_temperature_k=config["optics"]["incoming_load_temperature_k"],
                a2_over_delta_p=config["optics"]["hwpss_a2_over_delta_p"],
            )
        )
        log.info(
            "%s: Delta P_emission = %.3e W, Delta P_transmission = %.3e W, A_2 = %.3e W",
            name,
            rows[-1]["delta_p_emission_w"],
            rows[-1]["delta_p_transmission_w"],
            rows[-1]["a2_w"],
        )
    return pd.DataFrame(rows)


def run(config: dict, table_csv: str, fig_curves: str, fig_differential: str, fig_emission: str):
    """Write the HWP power table and Figs. 1 (curves), 2 (Delta P split), 3 (emission vs sky)."""
    table = hwp_power_table(config)
    write_csv(table, table_csv)
    log.info("wrote %s (%d channels)", table_csv, len(table))
    curves = {telescope: cfg.telescope_optics(config, telescope)[0] for telescope in ("MFT", "HFT")}
    hwp_temperature_k = {
        telescope: cfg.telescope_optics(config, telescope)[2] for telescope in ("MFT", "HFT")
    }
    hwp_figures.plot_curves(curves, table, fig_curves)
    hwp_figures.plot_differential_power(table, fig_differential)
    hwp_figures.plot_emission_vs_sky(
        curves, hwp_temperature_k, table, config["optics"]["t_cmb_k"], fig_emission
    )
    log.info("wrote figures %s, %s, %s", fig_curves, fig_differential, fig_emission)
