"""Rule noise_model: N_ell and C_FGres from the no-systematics residuals of all seeds."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import residual_spectra

setup_logging(snakemake.log[0])
residual_spectra.run_noise_model(list(snakemake.input.spectra), snakemake.output.model)
