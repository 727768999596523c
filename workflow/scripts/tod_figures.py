"""Rule tod_figures: Figs. 5, 6 and the notch transfer function."""

from hwp_tes_systematics.io import setup_logging, use_threads
from hwp_tes_systematics.stages import tod_figures

setup_logging(snakemake.log[0])
use_threads(snakemake.threads)  # litebird_sim's numba kernels
tod_figures.run(
    snakemake.params.config,
    kw_csv=snakemake.input.kw_conversion,
    fig_chunk=snakemake.output.fig_chunk,
    fig_spectra=snakemake.output.fig_spectra,
    fig_notch=snakemake.output.fig_notch,
)
