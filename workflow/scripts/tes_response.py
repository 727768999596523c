"""Rule tes_response: TES responsivity and g1, g2 per channel; Fig. 4."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import tes_response

setup_logging(snakemake.log[0])
tes_response.run(
    snakemake.params.tes,
    kw_csv=snakemake.input.kw_conversion,
    table_csv=snakemake.output.table,
    figure_png=snakemake.output.figure,
)
