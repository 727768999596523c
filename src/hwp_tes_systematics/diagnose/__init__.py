"""Diagnosis engine: where a recording differs from its simulation, and which physics is missing.

    recording = read_recording("recording.h5")        # litebird_sim HDF5 observation
    result = diagnose(recording, sky_iqu, a2_k, out_dir="diagnosis/")   # a Diagnosis
    result.mismatch_found, result.effect_names, result["unexplained"]
    result.parameter("tes_nonlinearity", "g1", 0)      # {value, sigma, unit, ...}

Modules: :mod:`.recording` (files), :mod:`.simulate` (recordings with injected effects, the
injection-only effects), :mod:`.testbed` (recordings with randomized nominal errors, for
the tests and the rates benchmark), :mod:`.model` (nominal model),
:mod:`.nominal` (nominal-model adjustments fitted on every recording), :mod:`.effects`
(catalog: one class per effect with its forward model, templates, signature and
evidence), :mod:`.noise` (noise estimate, Whittle), :mod:`.rolloff` (the detector's pole in the
noise), :mod:`.linalg` (whitened least
squares), :mod:`.locate` (lines, HWP-angle harmonics, transients, drifts, sky),
:mod:`.fit` (stepwise selection with the BIC), :mod:`.unexplained` (what no effect
explains), :mod:`.evidence` (measurements for the evidence texts), :mod:`.pipeline`
(``diagnose``), :mod:`.segments` (a recording longer than memory allows, diagnosed
segment by segment and combined), :mod:`.report` (diagnosis.json, diagnosis.md) and :mod:`.figures` (its
PNGs). Imports go one way: recording/model -> effects -> simulate;
effects -> locate -> nominal/fit/unexplained
-> pipeline -> segments; pipeline -> report -> figures (no cycle).
"""

from .effects import CATALOG, catalog_table
from .model import nominal_tod
from .pipeline import diagnose
from .recording import Recording, RecordingError, read_recording, write_recording
from .report import Diagnosis
from .simulate import simulate_recording

__all__ = [
    "CATALOG",
    "Diagnosis",
    "Recording",
    "RecordingError",
    "catalog_table",
    "diagnose",
    "nominal_tod",
    "read_recording",
    "simulate_recording",
    "write_recording",
]
