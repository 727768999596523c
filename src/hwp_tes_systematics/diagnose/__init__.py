"""Diagnosis engine: where a recording differs from its simulation, and which physics is missing.

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

__all__ = [
    "CATALOG",
    "Recording",
    "RecordingError",
    "catalog_table",
    "nominal_tod",
    "read_recording",
    "simulate_recording",
    "write_recording",
]
