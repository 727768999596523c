"""Rule analysis_mask: the common mask of the map-domain path from every fixed pass."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import map_domain_maps

setup_logging(snakemake.log[0])
map_domain_maps.run_mask(
    snakemake.params.config, list(snakemake.input.fixed), snakemake.output.mask
)
