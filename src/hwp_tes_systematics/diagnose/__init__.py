"""Diagnosis engine: where a recording differs from its simulation, and which physics is missing.

    recording = read_recording("recording.h5")        # litebird_sim HDF5 observation
    result = diagnose(recording, sky_iqu, a2_k, out_dir="diagnosis/")
    result["mismatch_found"], [e["name"] for e in result["effects"]], result["unexplained"]

Modules: :mod:`.recording` (files, simulated recordings), :mod:`.model` (nominal model),
:mod:`.nominal` (nominal-model adjustments fitted on every recording), :mod:`.effects`
(catalog: one class per effect with its forward model, templates, signature and
evidence), :mod:`.noise` (noise estimate, Whittle), :mod:`.linalg` (whitened least
squares), :mod:`.locate` (lines, HWP-angle harmonics, transients, drifts, sky),
:mod:`.fit` (stepwise selection with the BIC), :mod:`.unexplained` (what no effect
explains), :mod:`.evidence` (measurements for the evidence texts), :mod:`.pipeline`
(``diagnose``), :mod:`.report` (diagnosis.json, diagnosis.md) and :mod:`.figures` (its
PNGs). Imports go one way: recording/model -> effects -> locate -> nominal/fit/unexplained
-> pipeline -> report -> figures (no cycle).
"""

from .effects import CATALOG, catalog_table
from .model import nominal_tod
from .pipeline import diagnose
from .recording import (
    Recording,
    RecordingError,
    read_recording,
    simulate_recording,
    write_recording,
)

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
