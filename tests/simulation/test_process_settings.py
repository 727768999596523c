"""The process settings of a compute job (io.use_threads, io.reuse_freed_memory,
io.use_base_pages)."""

import os
import platform
import re
import subprocess
import sys
from pathlib import Path

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


# a 256 MB array written once: whether numpy still asked for huge pages (its switch's
# state), and the process's anonymous memory in transparent huge pages
HUGE_PAGES_OF_AN_ARRAY = """
import sys
import numpy as np
from numpy._core import multiarray
from hwp_tes_systematics.io import use_base_pages
print(use_base_pages() if sys.argv[1] == "base" else None)
array = np.ones(2**25)
print(multiarray._set_madvise_hugepage(False))
with open("/proc/self/smaps_rollup") as rollup:
    print(next(int(l.split()[1]) for l in rollup if l.startswith("AnonHugePages:")))
"""


def huge_pages_of_an_array(mode: str, **environment) -> tuple[str, str, int]:
    done = subprocess.run(
        [sys.executable, "-c", HUGE_PAGES_OF_AN_ARRAY, mode],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, **environment},
    )
    took, asked, kib = done.stdout.split()
    return took, asked, int(kib)


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps_rollup"), reason="Linux only")
def test_base_pages_keep_numpys_arrays_out_of_huge_pages_unless_numpy_is_told():
    """numpy asks for transparent huge pages for large arrays; after use_base_pages it no
    longer does, and where the kernel gives huge pages only when asked (policy
    ``madvise``) none of the process's memory is in them. Where the user set numpy's own
    switch (NUMPY_MADVISE_HUGEPAGE), it decides."""
    environment = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(os, "environ", environment)
        took, asked, huge_kib = huge_pages_of_an_array("base")
        assert (took, asked) == ("True", "False")
        policy = Path("/sys/kernel/mm/transparent_hugepage/enabled")
        if policy.exists() and "[madvise]" in policy.read_text():
            assert huge_kib == 0
        kernel = tuple(int(x) for x in re.findall(r"\d+", platform.release())[:2])
        if kernel >= (4, 6):  # numpy asks by default on these kernels
            assert huge_pages_of_an_array("default")[1] == "True"
        took, asked, _ = huge_pages_of_an_array("base", NUMPY_MADVISE_HUGEPAGE="1")
        assert (took, asked) == ("False", "True")
