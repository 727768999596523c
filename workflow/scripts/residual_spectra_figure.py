"""Rule residual_spectra_figure: BB of the CMB residual per case, means over seeds."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import residual_spectra

setup_logging(snakemake.log[0])
residual_spectra.run_figure(
    snakemake.params.config,
    {case: list(snakemake.input[case]) for case in snakemake.params.cases},
    list(snakemake.input.systematic),
    snakemake.output.figure,
    snakemake.output.table,
)
