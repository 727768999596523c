"""Rule component_separation: HILC of one (seed, case)."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import component_separation

setup_logging(snakemake.log[0])
component_separation.run(
    snakemake.params.config,
    seed=int(snakemake.wildcards.seed),
    case=snakemake.wildcards.case,
    map_paths=dict(snakemake.input.items()),
    out_h5=snakemake.output.hilc,
)
