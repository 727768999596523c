"""A channel's inputs computed from the configuration: its K/W conversion and nominal HWPSS
amplitude A_2 in K_CMB, its TES parameters, its sky maps. Library code shared by the
stages (kw_conversion, tod_figures, the diagnosis's example recording), the command
line and the diagnosis.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .. import config as cfg
from .. import sky
from ..instrument.channels import check_channel_name
from ..instrument.hwp_power import hwp_power_for_channel, sky_to_detector_efficiency
from ..instrument.radiometry import dpower_dtemperature_w_per_k, kelvin_per_watt
from ..instrument.tes import TesParameters, tes_parameters_for_channel


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
    channels, whose HWP the study takes as ideal), computed from the configured optics;
    a name the instrument model does not have is an error naming it (not A_2 = 0)."""
    check_channel_name(name, "channel_a2_k_cmb(name)", config["instrument"]["imo_location"])
    if name not in config["instrument"]["systematics_channels"]:
        return 0.0
    return channel_conversion(config, name)["a2_k_cmb"]


def tes_for_channel(tes_config: dict, p_nominal_w: float) -> TesParameters:
    """TES parameters from the config; the bias voltage is tuned per channel unless given."""
    physical = {
        key: tes_config[key]
        for key in (
            "tc_k",
            "tbath_k",
            "thermal_exponent_n",
            "rn_ohm",
            "transition_width_k",
            "critical_current_a",
            "thevenin_resistance_ohm",
        )
    }
    params = tes_parameters_for_channel(
        p_nominal_w,
        psat_factor=tes_config["psat_over_nominal_power"],
        resistance_fraction=tes_config["operating_resistance_fraction"],
        **physical,
    )
    if tes_config["bias_voltage_v"] is not None:
        params = replace(params, bias_voltage_v=tes_config["bias_voltage_v"])
    return params


def channel_sky(config: dict, channel, seed: int) -> dict:
    """sky.channel_sky_map of ``channel`` for realization ``seed`` with the configured nside,
    r, master seed and pysm3 data (CMB, foreground, total and the foreground source)."""
    nside = config["maps"]["nside"]
    return sky.channel_sky_map(
        channel,
        nside,
        3 * nside - 1,
        config["simulation"]["cmb_r"],
        config["master_seed"],
        seed,
        config["simulation"]["pysm_local_data"],
    )
