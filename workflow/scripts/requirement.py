"""Rule requirement: delta r versus sigma_g1, the fit and the requirement; Figs. 7, 8."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import requirement

setup_logging(snakemake.log[0])
requirement.run(
    snakemake.params.config,
    list(snakemake.input.likelihoods),
    table_csv=snakemake.output.table,
    requirement_json=snakemake.output.requirement,
    fig_likelihoods=snakemake.output.fig_likelihoods,
    fig_requirement=snakemake.output.fig_requirement,
)
