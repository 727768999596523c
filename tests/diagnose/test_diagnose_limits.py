"""A recording too large to diagnose is refused from its declared sizes, before any of its
data is read (diagnose.recording.check_memory); one whose datasets declare more than they
store (never written) is refused before that."""

import json

import h5py
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import RecordingError, read_recording
from hwp_tes_systematics.diagnose.recording_checks import (
    DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE,
    check_memory,
    diagnosis_memory_bytes,
)


def declared_file(path, n_samples, rate_hz=19.0, written=True, **create):
    """An HDF5 file in the recording layout whose datasets hold ``n_samples`` zeros per
    detector, or with ``written=False`` only declare them (unallocated: a few kB on disk);
    ``create``: h5py's dataset options (compression)."""

    def dataset(name, shape):
        if written:
            return handle.create_dataset(name, data=np.zeros(shape), **create)
        return handle.create_dataset(name, shape=shape, dtype="f8", **create)

    with h5py.File(path, "w") as handle:
        tod = dataset("tod", (2, n_samples))
        dataset("pointings", (2, n_samples, 3))
        dataset("hwp_angle", (n_samples,))
        tod.attrs["sampling_rate_hz"] = rate_hz
        tod.attrs["detectors"] = json.dumps(
            [{"name": f"d{k}", "pol_angle_rad": 0.0 if k == 0 else 1.5708} for k in range(2)]
        )
        tod.attrs["start_time"] = "63324.0"  # MJD, 2032-04-01
        tod.attrs["mjd_time"] = True
    return path


def test_a_file_declaring_1e10_samples_is_refused_before_reading(tmp_path):
    path = declared_file(tmp_path / "huge.h5", 10**10, written=False)
    assert path.stat().st_size < 1e6  # sparse: nothing to read, everything to allocate
    with pytest.raises(RecordingError) as info:
        read_recording(path)
    message = str(info.value)
    assert "huge.h5: dataset 'tod' declares shape (2, 10000000000) float64" in message
    assert "stores 0 bytes in the file: its data were never written" in message


def test_compressible_data_every_chunk_written_are_read(tmp_path):
    """Zeros under gzip store ~1/1000 of their bytes: read, since every chunk is stored;
    the same file with its chunks never written is refused, naming the chunks."""
    path = declared_file(tmp_path / "zeros.h5", 19 * 3600, compression="gzip")
    assert path.stat().st_size < 0.01 * 2 * 19 * 3600 * 8 * 5  # tod, pointings, HWP angle
    assert read_recording(path).tod.shape == (2, 19 * 3600)
    path = declared_file(tmp_path / "empty.h5", 19 * 3600, written=False, compression="gzip")
    with pytest.raises(RecordingError, match=r"'tod' .* but stores 0 bytes in the file \(0 of"):
        read_recording(path)


def test_a_recording_too_large_for_the_memory_says_the_segments():
    needed = diagnosis_memory_bytes(2, 10**10) / 2**30
    with pytest.raises(RecordingError) as info:
        check_memory("huge.h5", 2, 10**10, 19.0, budget_bytes=64 * 2**30)
    message = str(info.value)
    assert "huge.h5: declares 2 detector(s) x 1e+10 samples" in message
    assert f"~{needed:.3g} GiB" in message and "64 GiB available" in message
    assert "diagnose it in segments of at most" in message


def test_the_budget_sets_the_largest_piece(tmp_path):
    path = declared_file(tmp_path / "day.h5", 19 * 86400)
    budget = diagnosis_memory_bytes(2, 19 * 3600)  # one hour's worth
    with pytest.raises(RecordingError, match=r"segments of at most 1 h"):
        read_recording(path, memory_budget_bytes=budget)
    # within the budget, the same file is read
    recording = read_recording(path, memory_budget_bytes=diagnosis_memory_bytes(2, 19 * 86400))
    assert recording.tod.shape == (2, 19 * 86400)


def test_the_estimate_is_the_measured_slope():
    """~1.8 kB per detector-sample (benchmarks/diagnose_memory.py: 1808 B measured)."""
    assert 1800 <= DIAGNOSIS_BYTES_PER_DETECTOR_SAMPLE <= 2000
    one_day_pair = diagnosis_memory_bytes(2, 31 * 86400) / 2**30
    assert 9 < one_day_pair < 11  # GiB
