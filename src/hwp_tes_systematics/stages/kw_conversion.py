"""Stage: power-to-temperature conversion C [K/W] per channel and A_2 in K_CMB."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from .. import config as cfg
from ..hwp_power import hwp_power_for_channel, sky_to_detector_efficiency
from ..io import write_csv
from ..radiometry import dpower_dtemperature_w_per_k, kelvin_per_watt

log = logging.getLogger(__name__)


def conversion_row(config: dict, name: str, hwp: dict) -> dict:
    """One channel: C = delta T / delta P_opt (paper's four steps) and A_2 [K_CMB] = C A_2 [W].

    ``hwp`` is the channel's row of the HWP power table (p_nominal_w, a2_w).
    """
    t_cmb_k = config["optics"]["t_cmb_k"]
    delta_t_k = config["kw_conversion"]["delta_t_k"]
    channel = cfg.channel(config, name)
    curves, elements, _ = cfg.telescope_optics(config, channel.telescope)
    bandpass, efficiency = sky_to_detector_efficiency(channel, curves, elements)
    conversion = kelvin_per_watt(bandpass, efficiency, t_cmb_k, delta_t_k)
    analytic_w_per_k = dpower_dtemperature_w_per_k(bandpass, t_cmb_k, efficiency)
    row = {
        "channel": name,
        "telescope": channel.telescope,
        "bandcenter_ghz": channel.bandcenter_ghz,
        "bandwidth_ghz": channel.bandwidth_ghz,
        "sky_to_detector_efficiency": bandpass.integrate(efficiency)
        / bandpass.integrate(np.ones_like(efficiency)),
        "t_cmb_k": t_cmb_k,
        "delta_t_k": delta_t_k,
        **conversion,
        "kelvin_per_watt_analytic": 1.0 / analytic_w_per_k,
        "p_nominal_w": float(hwp["p_nominal_w"]),
        "a2_w": float(hwp["a2_w"]),
        "a2_k_cmb": float(hwp["a2_w"]) * conversion["kelvin_per_watt"],
    }
    if not (np.isfinite(row["kelvin_per_watt"]) and row["kelvin_per_watt"] > 0):
        raise ValueError(f"{name}: K/W factor {row['kelvin_per_watt']} is not finite > 0")
    return row


def kw_conversion_table(config: dict, hwp_table: pd.DataFrame) -> pd.DataFrame:
    """:func:`conversion_row` for every configured channel."""
    hwp_by_channel = hwp_table.set_index("channel")
    rows = []
    for name in cfg.selected_channels(config):
        if name not in hwp_by_channel.index:
            raise ValueError(f"channel {name} is missing from the HWP power table")
        rows.append(conversion_row(config, name, hwp_by_channel.loc[name]))
        log.info(
            "%s: C = %.4e K/W, A_2 = %.4e K_CMB",
            name,
            rows[-1]["kelvin_per_watt"],
            rows[-1]["a2_k_cmb"],
        )
    return pd.DataFrame(rows)


def channel_conversion(config: dict, name: str) -> dict:
    """:func:`conversion_row` of one channel computed from the configured optics alone."""
    channel = cfg.channel(config, name)
    curves, elements, hwp_temperature_k = cfg.telescope_optics(config, channel.telescope)
    hwp = hwp_power_for_channel(
        channel,
        curves,
        hwp_temperature_k,
        elements,
        config["optics"]["incoming_load_temperature_k"],
        config["optics"]["hwpss_a2_over_delta_p"],
    )
    return conversion_row(config, name, hwp)


def channel_a2_k_cmb(config: dict, name: str) -> float:
    """The nominal HWPSS amplitude A_2 [K_CMB] of one channel (0 outside the systematics
    channels, whose HWP the study takes as ideal), computed from the configured optics."""
    if name not in config["instrument"]["systematics_channels"]:
        return 0.0
    return channel_conversion(config, name)["a2_k_cmb"]


def run(config: dict, hwp_csv: str, table_csv: str) -> None:
    table = kw_conversion_table(config, pd.read_csv(hwp_csv))
    write_csv(table, table_csv)
    log.info("wrote %s (%d channels)", table_csv, len(table))
