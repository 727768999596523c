"""Rule hwp_power: HWP power table and Figs. 1-3."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import hwp_power

setup_logging(snakemake.log[0])
hwp_power.run(
    {"instrument": snakemake.params.instrument, "optics": snakemake.params.optics},
    table_csv=snakemake.output.table,
    fig_curves=snakemake.output.fig_curves,
    fig_differential=snakemake.output.fig_differential,
    fig_emission=snakemake.output.fig_emission,
)
