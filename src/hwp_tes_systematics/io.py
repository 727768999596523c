"""Small I/O helpers: atomic writes (temp file + rename), logging set-up and the process
settings of a compute job (threads, memory reuse)."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os
import sys
import tempfile
from pathlib import Path

import pandas as pd

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path beside ``path``; rename it to ``path`` only on success.

    Nothing half-written is left behind: on error the temporary file is removed.
    The temporary name keeps the final suffix so that writers that look at it
    (matplotlib, healpy, h5py) pick the right format.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}"
    )
    os.close(handle)
    os.unlink(temporary)  # writers create it themselves (healpy refuses to overwrite)
    try:
        yield Path(temporary)
        os.replace(temporary, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)


def write_csv(table: pd.DataFrame, path: str | Path, float_format: str = "%.10g") -> None:
    """Write a table as CSV atomically."""
    with atomic_path(path) as temporary:
        table.to_csv(temporary, index=False, float_format=float_format)


def setup_logging(log_path: str | Path | None = None, level: int = logging.INFO) -> None:
    """Log to stderr and, if given, to ``log_path`` (a rule's log file)."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if log_path is not None:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(log_path, mode="w"))
    logging.basicConfig(level=level, format=LOG_FORMAT, handlers=handlers, force=True)
    for chatty in ("healpy", "numba", "matplotlib"):
        logging.getLogger(chatty).setLevel(logging.WARNING)


def use_threads(threads: int) -> None:
    """Make the compiled kernels use ``threads`` threads (a rule's Snakemake ``threads``).

    numba's parallel loops (litebird_sim's dipole and coordinate kernels) are limited
    here; ducc0 (FFT, pixelisation) takes the count as an argument; Snakemake itself sets
    OMP_NUM_THREADS and OPENBLAS_NUM_THREADS (healpy, BLAS) for each job."""
    import numba

    threads = max(1, int(threads))
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def use_base_pages() -> bool:
    """Let numpy's large arrays take the kernel's base pages rather than transparent huge
    pages; returns whether the setting took effect (False where numpy's own switch,
    ``NUMPY_MADVISE_HUGEPAGE``, is set: it decides, as numpy documents).

    On Linux >= 4.6 numpy asks for huge pages (``madvise(MADV_HUGEPAGE)``) for every array
    of 4 MB and more; where the kernel's THP policy is ``madvise`` with ``defrag``
    ``madvise``, the first touch of each 2 MiB page waits for the kernel to compact memory
    for it. On the machine the diagnosis is measured on, 4 GiB written once take 14-28 s
    so against 1.6-2.0 s in base pages, and a diagnosis touches ~10 GB in its first
    segment (``docs/diagnosis/rates.md``). The numbers computed are the same bit for bit.
    Call it once at the start of a job's process, before its large arrays."""
    if not sys.platform.startswith("linux") or "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return False  # (numpy asks for huge pages on Linux only)
    try:
        from numpy._core import multiarray
    except ImportError:  # numpy < 2
        from numpy.core import multiarray
    switch = getattr(multiarray, "_set_madvise_hugepage", None)
    if switch is None:
        return False
    switch(False)
    return True


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_KEPT_FREE_BYTES = 2**31 - 1  # the largest trim threshold mallopt takes (a C int)


def reuse_freed_memory() -> bool:
    """Keep the memory a job frees for its next allocations (glibc's malloc; elsewhere
    nothing changes): returns whether the setting took effect.

    A TOD pass allocates and frees arrays of 10-300 MB per chunk (the TOD stack, its
    spectrum, the filtered rows). By default glibc serves each from a fresh ``mmap``
    and returns it to the kernel when freed, so every chunk faults its pages in again,
    each zero-filled by the kernel. With ``mmap`` off (M_MMAP_MAX = 0) and the heap's
    top kept (M_TRIM_THRESHOLD = 2 GiB), a freed array's pages serve the next one. The
    numbers computed are the same bit for bit. The process keeps what it freed: its
    resident memory stays near its peak, and the peak grows a little (measured on an
    8-day M1-140 fixed pass at nside 64: 1.50 -> 1.64 GB, flat from the third chunk
    on). Call it once at the start of a job's process (the stages that run TOD passes do)."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    kept = mallopt(_M_TRIM_THRESHOLD, _KEPT_FREE_BYTES) == 1
    return kept and mallopt(_M_MMAP_MAX, 0) == 1
