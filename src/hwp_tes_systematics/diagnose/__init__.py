"""Diagnosis engine: where a recording differs from its simulation, and which physics is missing.

    recording = read_recording("recording.h5")        # litebird_sim HDF5 observation
    result = diagnose(recording, sky_iqu, a2_k, out_dir="diagnosis/")
    result["mismatch_found"], [e["name"] for e in result["effects"]]

Modules: :mod:`.recording` (files, simulated recordings), :mod:`.model` (nominal model),
:mod:`.effects` (catalog of candidate effects), :mod:`.noise` (noise estimate, Whittle),
:mod:`.locate` (lines, HWP-angle harmonics, transients, drifts, sky), :mod:`.fit`
(stepwise selection with the BIC) and :mod:`.report` (``diagnose``).
"""

from .effects import CATALOG, catalog_table
from .model import nominal_tod
from .recording import (
    Recording,
    RecordingError,
    read_recording,
    simulate_recording,
    write_recording,
)
from .report import diagnose

__all__ = [
    "CATALOG",
    "Recording",
    "RecordingError",
    "catalog_table",
    "diagnose",
    "nominal_tod",
    "read_recording",
    "simulate_recording",
    "write_recording",
]
