"""Rule requirement: delta r versus sigma_g1, the requirements, the model check; Figs. 7, 8."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import requirement

setup_logging(snakemake.log[0])
seeds = sorted(snakemake.params.map_paths)
requirement.run(
    snakemake.params.config,
    list(snakemake.input.likelihoods),
    table_csv=snakemake.output.table,
    requirement_json=snakemake.output.requirement,
    answer_csv=snakemake.output.answer,
    fig_likelihoods=snakemake.output.fig_likelihoods,
    fig_requirement=snakemake.output.fig_requirement,
    fig_a2_scaling=snakemake.output.fig_a2_scaling,
    fig_ell_distribution=snakemake.output.fig_ell_distribution,
    noise_csv=snakemake.input.noise_model,
    nosys_spectra_csvs=list(snakemake.input.nosys_spectra),
    systematic_csvs=list(snakemake.input.systematic),
    instrument_csvs=list(snakemake.input.instruments),
    fig_fixed_instruments=snakemake.output.fig_fixed_instruments,
    template_fit_jsons=list(snakemake.input.template_fits),
    extension={
        "map_paths": snakemake.params.map_paths,
        "nosys_spectra": dict(zip(seeds, snakemake.input.nosys_spectra, strict=True)),
        "mask": snakemake.input.get("mask"),
    },
)
