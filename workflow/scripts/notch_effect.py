"""Rule notch_effect: the notch's transfer function on the CMB EE/BB spectra."""

from hwp_tes_systematics.io import setup_logging, use_threads
from hwp_tes_systematics.stages import notch_effect

setup_logging(snakemake.log[0])
use_threads(snakemake.threads)  # litebird_sim's numba kernels
notch_effect.run(
    snakemake.params.config,
    snakemake.params.channel,
    out_csv=snakemake.output.spectra[0],
    out_png=snakemake.output.figure[0],
)
