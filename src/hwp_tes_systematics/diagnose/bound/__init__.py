"""Step 5, bound: the nonlinearity g1 against the requirement of a workflow run
(:mod:`.requirement_check`; the step: :mod:`.step`)."""

from .requirement_check import load_requirement
from .step import bound_g1

__all__ = [
    "bound_g1",
    "load_requirement",
]
