"""Rule likelihood: r for every case of one realization, and the systematic-only bias."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import likelihood_fit

setup_logging(snakemake.log[0])
likelihood_fit.run(
    snakemake.params.config,
    seed=int(snakemake.wildcards.seed),
    spectra_csvs={case: snakemake.input[case] for case in snakemake.params.cases},
    noise_csv=snakemake.input.noise_model,
    systematic_csv=snakemake.input.systematic,
    out_json=snakemake.output.result,
)
