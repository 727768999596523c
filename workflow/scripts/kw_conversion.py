"""Rule kw_conversion: K/W factors and A_2 in K_CMB per channel."""

from hwp_tes_systematics.io import setup_logging
from hwp_tes_systematics.stages import kw_conversion

setup_logging(snakemake.log[0])
kw_conversion.run(
    {
        "instrument": snakemake.params.instrument,
        "optics": snakemake.params.optics,
        "kw_conversion": snakemake.params.kw_conversion,
    },
    hwp_csv=snakemake.input.hwp_power,
    table_csv=snakemake.output.table,
)
