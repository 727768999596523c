"""Step 6, report: the :class:`.diagnosis.Diagnosis` of the steps' outputs (:mod:`.step`),
written as ``diagnosis.json``, ``diagnosis.md`` (:mod:`.diagnosis`) and figures
(:mod:`.figures`)."""

from .diagnosis import Diagnosis, ReportPaths, markdown_report, write_outputs
from .step import report

__all__ = [
    "Diagnosis",
    "ReportPaths",
    "markdown_report",
    "report",
    "write_outputs",
]
