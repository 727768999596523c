"""Random streams derived from one master seed plus names (channel, seed, detector, ...).

Each stream is ``numpy.random.Generator(PCG64(SeedSequence(master_seed, spawn_key)))``
with the spawn key made from the names by a stable hash, so a draw depends only on
what it is for, never on the order in which jobs run.
"""

from __future__ import annotations

import hashlib

import numpy as np


def _stable_int(name) -> int:
    """A stable 32-bit integer for a name (int, str, ...), independent of PYTHONHASHSEED."""
    digest = hashlib.sha256(repr(name).encode()).digest()
    return int.from_bytes(digest[:4], "little")


def seed_sequence(master_seed: int, *names) -> np.random.SeedSequence:
    """SeedSequence for the stream identified by ``names`` under ``master_seed``."""
    return np.random.SeedSequence(int(master_seed), spawn_key=tuple(_stable_int(n) for n in names))


def rng(master_seed: int, *names) -> np.random.Generator:
    """Generator for the stream ``names``, e.g. rng(master, "noise", "M1-140", 3, "det_T")."""
    return np.random.Generator(np.random.PCG64(seed_sequence(master_seed, *names)))


def integer_seed(master_seed: int, *names) -> int:
    """A 32-bit integer seed for libraries that take an int (e.g. litebird_sim's user_seed)."""
    return int(seed_sequence(master_seed, *names).generate_state(1)[0])
