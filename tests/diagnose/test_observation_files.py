"""The detectors of one observation written to several files, read and diagnosed as one
recording (:func:`.recording.merge_recordings`)."""

from __future__ import annotations

import dataclasses
import json

import astropy.units as u
import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.cli import main
from hwp_tes_systematics.diagnose import read_recording, simulate_recording, write_recording
from hwp_tes_systematics.diagnose.recording_checks import RecordingError, recording_size
from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, sky_map

pytestmark = pytest.mark.slow


def _detector(recording, k: int):
    """Detector k of ``recording`` alone."""
    return dataclasses.replace(
        recording,
        tod=recording.tod[k : k + 1],
        pointings_ecl=recording.pointings_ecl[k : k + 1],
        detectors=[recording.detectors[k]],
        flags=recording.flags[k : k + 1],
        observation=None,
    )


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    """A nonlinear pair (g1 = 0.02 K^-1) written one detector per file."""
    folder = tmp_path_factory.mktemp("split")
    recording = simulate_recording(
        CHANNEL, 1.0, MASTER_SEED, 3, sky_map(), A2_K, [("tes_nonlinearity", {"g1": 0.02})]
    )
    paths = [folder / f"det{k}.h5" for k in range(2)]
    for k, path in enumerate(paths):
        write_recording(path, _detector(recording, k))
    return recording, paths


def test_the_files_of_one_observation_read_as_one_recording(split):
    recording, paths = split
    merged = read_recording(paths)
    assert recording_size(paths) == (2, recording.n_samples, recording.sampling_rate_hz)
    np.testing.assert_array_equal(merged.tod, recording.tod)
    np.testing.assert_array_equal(merged.pointings_ecl, recording.pointings_ecl)
    assert merged.detector_names == recording.detector_names
    assert merged.channel == CHANNEL
    assert merged.source == f"{paths[0]} + {paths[1]}"
    segment = read_recording(paths, samples=(100, 400))  # a segment of both
    np.testing.assert_array_equal(segment.tod, recording.tod[:, 100:400])


def test_files_of_different_observations_are_refused_naming_them(split, tmp_path):
    recording, paths = split
    later = dataclasses.replace(_detector(recording, 1), start_time=recording.start_time + 60 * u.s)
    write_recording(tmp_path / "later.h5", later)
    with pytest.raises(RecordingError, match="start .* apart: not the same observation"):
        read_recording([paths[0], tmp_path / "later.h5"])
    with pytest.raises(RecordingError, match=r"detector\(s\) .* in more than one file"):
        read_recording([paths[0], paths[0]])
    short = dataclasses.replace(
        _detector(recording, 1),
        tod=recording.tod[1:, :-10],
        times_s=recording.times_s[:-10],
        hwp_angle_rad=recording.hwp_angle_rad[:-10],
        pointings_ecl=recording.pointings_ecl[1:, :-10],
        flags=recording.flags[1:, :-10],
    )
    write_recording(tmp_path / "short.h5", short)
    with pytest.raises(RecordingError, match="not one observation"):
        recording_size([paths[0], tmp_path / "short.h5"])


def test_the_command_line_diagnoses_the_files_as_one_recording(split, tmp_path):
    _, paths = split
    sky = tmp_path / "sky.fits"
    hp.write_map(sky, sky_map(), dtype=np.float64)
    out = tmp_path / "out"
    code = main(["diagnose", *map(str, paths), "--sky", str(sky), "--out", str(out), "-q"])
    assert code == 0
    result = json.loads((out / "diagnosis.json").read_text())
    first = result["effects"][0]
    assert first["name"] == "tes_nonlinearity"
    for k in range(2):
        g1 = [p for p in first["parameters"].values() if p["parameter"] == "g1"][k]
        assert abs(g1["value"] - 0.02) < 3 * g1["sigma"]
