"""Rule example_recording: a recording with the electrothermal TES nonlinearity."""

from hwp_tes_systematics.io import setup_logging, use_threads
from hwp_tes_systematics.stages import diagnose_recordings

setup_logging(snakemake.log[0])
use_threads(snakemake.threads)  # litebird_sim's numba kernels
diagnose_recordings.make_example(
    snakemake.params.config, snakemake.output.recording, snakemake.output.sky
)
