"""Rule residual_spectra: spectra of the CMB residual of one (seed, case)."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import residual_spectra

setup_logging(snakemake.log[0])
residual_spectra.run(snakemake.input.hilc, snakemake.output.spectra)
