"""Diagnosis engine: where a recording differs from its simulation, and which physics is missing.

    recording = read_recording("recording.h5")        # litebird_sim HDF5 observation
    result = diagnose(recording, sky_iqu, a2_k, out_dir="diagnosis/")   # a Diagnosis
    result.mismatch_found, result.effect_names, result["unexplained"]
    result.parameter("tes_nonlinearity", "g1", 0)      # {value, sigma, unit, ...}

The layout follows the diagnosis. Ground floor: :mod:`.recording` (files) and
:mod:`.recording_checks` (their declared sizes and memory), :mod:`.model` (the nominal
model d_nom), :mod:`.noise` (noise estimate, Whittle) and :mod:`.linalg` (whitened least
squares). The physics: :mod:`.effects`, the catalog, one class per effect with its forward
model, templates, signature, evidence and, for the effects seen in the noise, its own fit
(:mod:`.effects.fluctuations`, :mod:`.effects.rolloff`); :mod:`.catalog` writes its page.
The six steps, one folder each, chained by :mod:`.pipeline` (``diagnose``):

    1 :mod:`.nominal`   the nominal adjustments (gain, offsets, 2f, angles, sky, noise)
    2 :mod:`.locate`    lines, HWP-angle harmonics, transients, drifts, sky
    3 :mod:`.select`    stepwise selection with the BIC over the template bank
    4 :mod:`.explain`   each effect's evidence and look-alikes; what no effect explains
    5 :mod:`.bound`     g1 against a workflow run's requirement
    6 :mod:`.report`    diagnosis.json, diagnosis.md and the figures

Above them, :mod:`.segments` diagnoses a recording longer than memory allows segment by
segment; beside them, :mod:`.simulate` and :mod:`.testbed` make recordings with a known
truth for the tests and the rates benchmark. Imports go one way: ground -> effects ->
steps 1 to 6 (a step imports only earlier ones) -> pipeline -> segments.
"""

from .effects import CATALOG, catalog_table
from .model import nominal_tod
from .pipeline import diagnose
from .recording import Recording, read_recording, write_recording
from .recording_checks import RecordingError
from .report.diagnosis import Diagnosis
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
