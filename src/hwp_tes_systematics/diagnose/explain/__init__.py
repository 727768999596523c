"""Step 4, explain: each selected effect's parameters, evidence (:mod:`.evidence`) and
look-alikes (:mod:`.step`), and the structure no effect explains (:mod:`.unexplained`)."""

from .evidence import Evidence
from .step import explain_effects, left_at_its_signature, look_alikes, merge_members
from .unexplained import find_unexplained

__all__ = [
    "Evidence",
    "explain_effects",
    "find_unexplained",
    "left_at_its_signature",
    "look_alikes",
    "merge_members",
]
