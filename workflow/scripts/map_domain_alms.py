"""Rule map_domain_alms: every seed's a_lm of one channel from its fixed pass."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import map_domain_maps

setup_logging(snakemake.log[0])
map_domain_maps.run_seeds(
    snakemake.params.config,
    channel_name=snakemake.wildcards.channel,
    seeds=snakemake.params.seeds,
    fixed_h5=snakemake.input.fixed,
    mask_h5=snakemake.input.mask,
    out_h5s=snakemake.output.alms,
    pooled_h5s=list(snakemake.input.pooled),
)
