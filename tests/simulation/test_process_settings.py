"""The process settings of a compute job (io.use_threads, io.reuse_freed_memory)."""

import subprocess
import sys

import pytest

# a 512 MB array touched and freed, then the same size again: the page faults of the second
FAULTS_OF_A_REALLOCATION = """
import resource, sys
import numpy as np
from hwp_tes_systematics.io import reuse_freed_memory
if sys.argv[1] == "reuse":
    assert reuse_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
first = np.ones(2**26)
del first
before = faults()
second = np.ones(2**26)
print(faults() - before)
"""


def faults_of_a_reallocation(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", FAULTS_OF_A_REALLOCATION, mode],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(done.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_freed_memory_serves_the_next_array_without_page_faults():
    """By default a freed 512 MB array goes back to the kernel and the next one faults its
    pages in again (zero-filled); with reuse_freed_memory the freed pages serve it."""
    default, reused = faults_of_a_reallocation("default"), faults_of_a_reallocation("reuse")
    assert default > 100, default
    assert reused < default / 10, (reused, default)
