"""Rule systematic_spectra: the systematic alone through the no-systematics HILC weights."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import residual_spectra

setup_logging(snakemake.log[0])
maps = {key: value for key, value in snakemake.input.items() if key != "nosys_hilc"}
residual_spectra.run_systematic(
    snakemake.params.config,
    seed=int(snakemake.wildcards.seed),
    map_paths=maps,
    nosys_hilc_h5=snakemake.input.nosys_hilc,
    out_csv=snakemake.output.spectra,
)
