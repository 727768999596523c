"""Rule component_separation: HILC of one seed, every case, and the systematic-only spectra."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import component_separation

setup_logging(snakemake.log[0])
component_separation.run(
    snakemake.params.config,
    seed=int(snakemake.wildcards.seed),
    cases=list(snakemake.params.cases),
    map_paths={name: path for name, path in snakemake.input.items() if name != "mask"},
    out_h5s=list(snakemake.output.hilc),
    systematic_csv=snakemake.output.systematic,
    instruments_csv=snakemake.output.instruments,
    fixed_instruments=snakemake.params.fixed_instruments,
    mask_path=snakemake.input.get("mask"),
    template_fit_json=snakemake.output.template_fit,
)
