"""Rule component_separation: HILC of one seed, every case, and the systematic-only spectra."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import component_separation

setup_logging(snakemake.log[0])
component_separation.run(
    snakemake.params.config,
    seed=int(snakemake.wildcards.seed),
    cases=list(snakemake.params.cases),
    map_paths=dict(snakemake.input.items()),
    out_h5s=list(snakemake.output.hilc),
    systematic_csv=snakemake.output.systematic,
)
