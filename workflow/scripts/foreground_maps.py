"""Rule foreground_maps: one FITS map per channel."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import foreground_maps

setup_logging(snakemake.log[0])
foreground_maps.run(snakemake.params.config, snakemake.params.channels, snakemake.output.maps)
