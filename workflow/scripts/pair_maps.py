"""Rule pair_maps: TOD -> notch -> binned maps and g1 templates for one (channel, seed)."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import pair_maps

setup_logging(snakemake.log[0])
pair_maps.run(
    snakemake.params.config,
    channel_name=snakemake.wildcards.channel,
    seed=int(snakemake.wildcards.seed),
    kw_csv=snakemake.input.kw_conversion,
    foreground_fits=snakemake.input.foreground,
    out_h5=snakemake.output.maps,
    threads=snakemake.threads,
)
