"""Rule diagnose: diagnosis of one recording."""

from hwp_tes_systematics.io import setup_logging, use_threads
from hwp_tes_systematics.stages import diagnose_recordings

setup_logging(snakemake.log[0])
use_threads(snakemake.threads)  # litebird_sim's numba kernels
diagnose_recordings.run(
    snakemake.params.config,
    recording_h5=snakemake.input.recording,
    sky_fits=snakemake.input.sky,
    out_json=snakemake.output.diagnosis,
    out_md=snakemake.output.report,
)
