"""Stage: power-to-temperature conversion C [K/W] per channel and A_2 in K_CMB."""

from __future__ import annotations

import logging

import pandas as pd

from .. import config as cfg
from ..io import write_csv
from ..simulation.channel_inputs import conversion_row

log = logging.getLogger(__name__)


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


def run(config: dict, hwp_csv: str, table_csv: str) -> None:
    table = kw_conversion_table(config, pd.read_csv(hwp_csv))
    write_csv(table, table_csv)
    log.info("wrote %s (%d channels)", table_csv, len(table))
