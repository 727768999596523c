"""Rule fixed_pass: the seed-independent TOD pass of one channel (map-domain path)."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import map_domain_maps

setup_logging(snakemake.log[0])
map_domain_maps.run_fixed_pass(
    snakemake.params.config,
    channel_name=snakemake.wildcards.channel,
    kw_csv=snakemake.input.kw_conversion,
    foreground_fits=snakemake.input.foreground,
    out_h5s=dict(zip(snakemake.params.variants, snakemake.output.fixed, strict=True)),
    threads=snakemake.threads,
)
