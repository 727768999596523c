"""A recording file's declared sizes, dtypes and stored bytes, and the memory its diagnosis
needs, checked before any of its data is read (:mod:`.recording`, "Declared sizes")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

MIN_SAMPLES = 64
# What diagnosing a recording needs in memory, checked from the declared sizes before
# anything is read: the peak RSS of diagnose() grows by 1808 B per detector-sample
# (M1-140 pair at 31 Hz, 2 h -> 6 h: 552 -> 2091 MiB above the 457-625 MiB of the loaded
# package; `python benchmarks/diagnose_memory.py --hours 2 6`, with the smooth gain drift's
# templates; 1269 B before them; 14 detectors on two wafers with the group forms, 1 -> 2 h
# at 19 Hz: 1514 B), on top of ~0.7 GB.
DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE = 1850
DIAGNOSIS_BASE_BYTES = 0.7e9
# A dataset (tod, pointings, hwp_angle, RLE flags) storing less than 1/this of the bytes
# its shape declares is either compressible data (accepted if every chunk is stored) or
# never written (refused): gzip on float64 TOD, pointing or HWP angle gains < 10x; a
# dataset created with a shape and never written stores nothing.
MAX_DECLARED_OVER_STORED = 100
REAL_KINDS = "fiu"  # numpy dtype kinds accepted for tod, pointings, hwp_angle
FLAG_KINDS = "biu"  # for flags and RLE flags


class RecordingError(ValueError):
    """A recording file that cannot be used; the message names the file and the problem."""


def fail(path, problem: str):
    """Raise a :class:`RecordingError` naming ``path`` and ``problem``."""
    raise RecordingError(f"{path}: {problem}")


def rle_flag_names(handle) -> list[str]:
    """The names of an open file's per-detector RLE flag datasets (``flags_<k>``), sorted."""
    return sorted(name for name in handle if name.startswith("flags_") and name[6:].isdigit())


def _check_flags(path, handle, n_det: int, n: int) -> None:
    """The flags' declared shapes and dtypes, and the RLE flags' run lengths, checked
    before any flag array of the recording's size is made."""
    import h5py

    if "flags" in handle:
        flags = handle["flags"]
        if not isinstance(flags, h5py.Dataset):
            fail(path, "'flags' is not a dataset: expected (n_det, n_samples) booleans")
        if flags.shape != (n_det, n):
            fail(path, f"dataset 'flags' has shape {flags.shape}, expected {(n_det, n)}")
        _check_dtype(path, "flags", flags, FLAG_KINDS, "booleans or integers (non-zero = bad)")
    for name in rle_flag_names(handle):
        index = int(name[6:])
        if index >= n_det:
            fail(path, f"dataset {name!r} refers to detector {index} of {n_det}")
        dataset = handle[name]
        if not isinstance(dataset, h5py.Dataset) or dataset.ndim != 2 or dataset.shape[0] != 2:
            shape = getattr(dataset, "shape", "a group")
            fail(
                path,
                f"dataset {name!r} has shape {shape}: expected (2, n_runs), run lengths "
                "then values (litebird_sim's run-length-encoded flags)",
            )
        if dataset.shape[1] > n:
            fail(
                path,
                f"dataset {name!r} declares {dataset.shape[1]} runs, more than the {n} "
                "samples of 'tod' (expected at most one run per sample)",
            )
        _check_dtype(path, name, dataset, FLAG_KINDS, "integer run lengths and flag values")
        _check_stored(path, name, dataset)
        runs = np.asarray(dataset[0], dtype=np.int64) if dataset.shape[1] else np.zeros(0)
        if (runs < 0).any():
            fail(path, f"dataset {name!r} has negative run lengths: expected lengths >= 0")
        if int(runs.sum()) != n:
            fail(
                path,
                f"dataset {name!r} decodes to {int(runs.sum())} samples, 'tod' has {n} "
                "(expected the run lengths to add up to the samples of 'tod')",
            )


def recording_size(path) -> tuple[int, int, float]:
    """(detectors, samples, sampling rate [Hz]) a recording file declares, its datasets'
    shapes checked and none of its data read; of a list of files of one observation, their
    detectors summed (their samples and rates must agree)."""
    import h5py

    if isinstance(path, (list, tuple)):
        sizes = [recording_size(p) for p in path]
        if len({size[1:] for size in sizes}) > 1:
            listed = ", ".join(f"{p}: {n} samples at {r:g} Hz" for p, (_, n, r) in zip(path, sizes))
            fail(", ".join(map(str, path)), f"not one observation ({listed})")
        return sum(size[0] for size in sizes), sizes[0][1], sizes[0][2]
    path = Path(path)
    try:
        check_file(path)
        if is_toast_file(path):
            from .toast_recording import toast_layout

            return toast_layout(path)[:3]
        with h5py.File(path, "r") as handle:
            _, n_det, n, sampling_rate_hz = declared_layout(path, handle)
    except OSError as error:
        fail(path, f"cannot be read as HDF5 ({error}): the file is truncated or corrupt")
    return n_det, n, sampling_rate_hz


def diagnosis_memory_bytes(n_detectors: int, n_samples: int) -> float:
    """The memory diagnosing a recording of this size needs [bytes] (estimate, see
    DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE)."""
    return DIAGNOSIS_BASE_BYTES + DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE * n_detectors * n_samples


def available_memory_bytes() -> float:
    """The memory the system can give this process now [bytes] (psutil)."""
    import psutil

    return float(psutil.virtual_memory().available)


def check_memory(path, n_det: int, n: int, sampling_rate_hz: float, budget_bytes=None) -> None:
    """Refuse, before reading, a recording whose diagnosis would not fit ``budget_bytes``
    (default: the available memory), saying the sizes and what to do."""
    budget = available_memory_bytes() if budget_bytes is None else float(budget_bytes)
    needed = diagnosis_memory_bytes(n_det, n)
    if needed <= budget:
        return
    per_segment = max(0.0, budget - DIAGNOSIS_BASE_BYTES) / (
        DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE * n_det
    )
    hours = n / sampling_rate_hz / 3600.0
    fail(
        path,
        f"declares {n_det} detector(s) x {n:.4g} samples ({hours:.4g} h at "
        f"{sampling_rate_hz:g} Hz): diagnosing it needs ~{needed / 2**30:.3g} GiB "
        f"(~{DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE} B per detector-sample), more than the "
        f"{budget / 2**30:.3g} GiB available; diagnose it in segments of at most "
        f"{per_segment / sampling_rate_hz / 3600.0:.3g} h (the command line does so by "
        "itself, --segment-hours; from Python: diagnose.segments.diagnose_segments), or on "
        "a machine with more memory",
    )


def is_toast_file(path) -> bool:
    """True if ``path`` is a TOAST 3 observation file (its root attribute
    ``toast_format_version``; read by :mod:`.toast_recording`)."""
    import h5py

    with h5py.File(path, "r") as handle:
        return "toast_format_version" in handle.attrs


def check_file(path: Path) -> None:
    """An existing HDF5 file at ``path``, else a :class:`RecordingError`."""
    import h5py

    if not path.exists():
        fail(path, "no such file")
    if not path.is_file() or not h5py.is_hdf5(path):
        fail(path, "not an HDF5 file (expected a litebird_sim or TOAST 3 observation file)")


def declared_layout(path: Path, handle) -> tuple:
    """(tod dataset, detectors, samples, sampling rate) of an open file, shapes checked."""
    import h5py

    for name in ("tod", "pointings", "hwp_angle"):
        if name not in handle or not isinstance(handle[name], h5py.Dataset):
            hint = (
                " (write the observation with write_full_pointings=True)" if name != "tod" else ""
            )
            fail(path, f"missing dataset {name!r}{hint}")
    dataset = handle["tod"]
    if dataset.ndim != 2:
        fail(path, f"dataset 'tod' has shape {dataset.shape}, expected (n_det, n_samples)")
    for name in ("tod", "pointings", "hwp_angle"):
        _check_dtype(path, name, handle[name], REAL_KINDS, "real numbers (float64)")
        _check_stored(path, name, handle[name])
    n_det, n = dataset.shape
    if n < MIN_SAMPLES or n_det < 1:
        fail(path, f"dataset 'tod' has shape {dataset.shape}: too few samples/detectors")
    pointings = handle["pointings"]
    if pointings.shape != (n_det, n, 3):
        fail(
            path,
            f"length mismatch: 'pointings' has shape {pointings.shape}, 'tod' {(n_det, n)} "
            f"(expected {(n_det, n, 3)})",
        )
    hwp = handle["hwp_angle"]
    if hwp.shape != (n,):
        fail(path, f"length mismatch: 'hwp_angle' has shape {hwp.shape}, 'tod' has {n} samples")
    try:
        sampling_rate_hz = float(dataset.attrs["sampling_rate_hz"])
    except KeyError:
        fail(path, "dataset 'tod' has no 'sampling_rate_hz' attribute")
    except (TypeError, ValueError):
        fail(
            path,
            f"attribute 'sampling_rate_hz' of dataset 'tod' = "
            f"{dataset.attrs['sampling_rate_hz']!r}: expected a number of Hz",
        )
    if not (math.isfinite(sampling_rate_hz) and sampling_rate_hz > 0):
        fail(path, f"sampling_rate_hz = {sampling_rate_hz!r}: expected a rate > 0 Hz")
    _check_flags(path, handle, n_det, n)
    return dataset, n_det, n, sampling_rate_hz


def _check_dtype(path, name: str, dataset, kinds: str, expected: str) -> None:
    if dataset.dtype.kind not in kinds or dataset.dtype.names is not None:
        fail(path, f"dataset {name!r} has dtype {dataset.dtype}: expected {expected}")


def _check_stored(path, name: str, dataset) -> None:
    """Refuse a dataset whose data were never (all) written: its stored bytes are below
    1/MAX_DECLARED_OVER_STORED of what its shape declares and, chunked, not every chunk
    is stored (a written chunk of compressible data is stored however small). A virtual
    or external dataset is not checked here (the memory check still applies)."""
    if dataset.is_virtual or dataset.external:
        return
    declared = math.prod(dataset.shape) * dataset.dtype.itemsize
    stored = dataset.id.get_storage_size()
    if not declared or (stored and stored * MAX_DECLARED_OVER_STORED >= declared):
        return
    detail = ""
    if dataset.chunks is not None:  # counted only here: the count reads the chunk index
        expected = math.prod(
            -(-size // chunk) for size, chunk in zip(dataset.shape, dataset.chunks, strict=True)
        )
        written = dataset.id.get_num_chunks()
        if written >= expected:
            return
        detail = f" ({written} of its {expected} chunks)"
    fail(
        path,
        f"dataset {name!r} declares shape {dataset.shape} {dataset.dtype} "
        f"({declared / 2**30:.3g} GiB) but stores {stored} bytes in the file{detail}: its "
        "data were never written (expected every sample written); write the recording again",
    )
