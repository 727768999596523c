"""Rule foreground_maps: the FITS map of one channel."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import foreground_maps

setup_logging(snakemake.log[0])
foreground_maps.run(snakemake.params.config, [snakemake.wildcards.channel], [snakemake.output.maps])
