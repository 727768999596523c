"""Rule requirement: delta r versus sigma_g1 by two estimators, the requirements; Figs. 7, 8."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import requirement

setup_logging(snakemake.log[0])
seeds = sorted(snakemake.params.map_paths)
requirement.run(
    snakemake.params.config,
    list(snakemake.input.likelihoods),
    table_csv=snakemake.output.table,
    requirement_json=snakemake.output.requirement,
    fig_likelihoods=snakemake.output.fig_likelihoods,
    fig_requirement=snakemake.output.fig_requirement,
    fig_a2_scaling=snakemake.output.fig_a2_scaling,
    extension={
        "map_paths": snakemake.params.map_paths,
        "nosys_spectra": dict(zip(seeds, snakemake.input.nosys_spectra, strict=True)),
        "noise_csv": snakemake.input.noise_model,
        "notch_csv": snakemake.input.get("notch"),
    },
)
