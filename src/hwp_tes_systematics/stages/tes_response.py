"""Stage: TES electrothermal response at each channel's nominal load; g1, g2; Fig. 4."""

from __future__ import annotations

import logging

import pandas as pd

from ..figures.tes import plot_response_curve
from ..instrument.tes import (
    nonlinearity_coefficients,
    optical_power_for_resistance,
    solve_operating_point,
)
from ..io import write_csv
from ..simulation.channel_inputs import tes_for_channel

log = logging.getLogger(__name__)

# Expansion range when a channel has no HWPSS (ideal HWP): +-2 % of the nominal load.
MIN_HALF_RANGE_OVER_NOMINAL = 0.02


def expansion_half_range_w(p_nominal_w: float, a2_w: float) -> float:
    """The range of the expansion: the HWPSS swing |A_2|, at least 2 % of the load."""
    return max(abs(a2_w), MIN_HALF_RANGE_OVER_NOMINAL * p_nominal_w)


def tes_response_table(tes_config: dict, kw_table: pd.DataFrame) -> pd.DataFrame:
    """Per channel: operating point, responsivity, saturation, g1 [1/K] and g2 [1/K^2]."""
    rows = []
    for _, channel in kw_table.iterrows():
        p_nominal_w = float(channel["p_nominal_w"])
        params = tes_for_channel(tes_config, p_nominal_w)
        point = solve_operating_point(params, p_nominal_w)
        half_range_w = expansion_half_range_w(p_nominal_w, float(channel["a2_w"]))
        p_saturation_w = optical_power_for_resistance(params, 0.99)
        coefficients = nonlinearity_coefficients(
            params, p_nominal_w, float(channel["kelvin_per_watt"]), half_range_w
        )
        rows.append(
            {
                "channel": channel["channel"],
                "p_nominal_w": p_nominal_w,
                "psat_w": params.psat_w,
                "p_optical_saturation_w": p_saturation_w,
                "bias_voltage_v": params.bias_voltage_v,
                "operating_temperature_k": float(point.temperature_k),
                "operating_resistance_ohm": float(point.resistance_ohm),
                "operating_current_a": float(point.current_a),
                "hwpss_half_range_w": half_range_w,
                "saturates_with_hwpss": bool(p_nominal_w + half_range_w >= p_saturation_w),
                "kelvin_per_watt": float(channel["kelvin_per_watt"]),
                "responsivity_a_per_w": coefficients["responsivity_a_per_w"],
                "dsdp_a_per_w2": coefficients["dsdp_a_per_w2"],
                "g1_per_k": coefficients["g1_per_k"],
                "g2_per_k2": coefficients["g2_per_k2"],
            }
        )
        log.info(
            "%s: S0 = %.3e A/W, g1 = %.3e 1/K, g2 = %.3e 1/K^2",
            channel["channel"],
            rows[-1]["responsivity_a_per_w"],
            rows[-1]["g1_per_k"],
            rows[-1]["g2_per_k2"],
        )
    return pd.DataFrame(rows)


def run(tes_config: dict, kw_csv: str, table_csv: str, figure_png: str) -> None:
    """Write the TES response table and the response-curve figure of tes.figure_channel."""
    kw_table = pd.read_csv(kw_csv)
    table = tes_response_table(tes_config, kw_table)
    write_csv(table, table_csv)
    log.info("wrote %s (%d channels)", table_csv, len(table))
    name = tes_config["figure_channel"]
    if name not in set(kw_table["channel"]):
        raise ValueError(
            f"tes.figure_channel = {name!r} is not among the simulated channels "
            f"{list(kw_table['channel'])}"
        )
    channel = kw_table.set_index("channel").loc[name]
    plot_response_curve(
        tes_for_channel(tes_config, float(channel["p_nominal_w"])),
        float(channel["p_nominal_w"]),
        abs(float(channel["a2_w"])),
        name,
        figure_png,
    )
    log.info("wrote %s", figure_png)
