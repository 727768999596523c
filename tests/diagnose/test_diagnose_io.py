"""Recordings on disk (litebird_sim's HDF5 format), the nominal model, and bad input."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import (
    RecordingError,
    nominal_tod,
    read_recording,
    simulate_recording,
    write_recording,
)
from hwp_tes_systematics.diagnose.model import SkyMapError
from hwp_tes_systematics.diagnose.testbed import (
    A2_K,
    CHANNEL,
    MASTER_SEED,
    recorded,
    run,
    sky_map,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def clean_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("io") / "clean.h5"
    recording = simulate_recording(CHANNEL, 0.5, MASTER_SEED, 7, sky_map(), A2_K)
    write_recording(path, recording)
    return path, recording


def test_file_round_trip(clean_file):
    path, recording = clean_file
    read = read_recording(path)
    np.testing.assert_array_equal(read.tod, recording.tod)  # float64 on disk, not float32
    np.testing.assert_array_equal(read.pointings_ecl, recording.pointings_ecl)
    np.testing.assert_array_equal(read.hwp_angle_rad, recording.hwp_angle_rad)
    assert read.start_time.scale == "tdb"
    assert abs((read.start_time - recording.start_time).to_value("s")) < 1e-6
    assert read.detector_names == recording.detector_names
    np.testing.assert_array_equal(read.pol_angles_rad, recording.pol_angles_rad)
    assert not read.flags.any()
    assert read.channel == CHANNEL
    from litebird_sim.io import read_one_observation

    # litebird_sim itself reads the file too
    observation = read_one_observation(path, tod_dtype=np.float64)
    np.testing.assert_array_equal(observation.tod, recording.tod)


def test_nominal_model_equals_the_simulation_without_noise(tmp_path):
    """d_nom from the FILE's pointing and start time reproduces the injected sky+dipole+HWPSS."""
    noiseless = simulate_recording(
        CHANNEL,
        0.5,
        MASTER_SEED,
        0,
        sky_map(),
        A2_K,
        [("noise_mismatch", {"net_ukrts": 0.0, "fknee_mhz": 0.0})],
    )
    write_recording(tmp_path / "noiseless.h5", noiseless)
    read = read_recording(tmp_path / "noiseless.h5")
    model = nominal_tod(read, sky_map(), A2_K)
    assert np.abs(model - noiseless.tod).max() < 1e-9
    assert np.abs(noiseless.tod).max() > 0.2  # the HWPSS is there


def test_nan_stretch_is_masked_not_propagated(clean_file, tmp_path):
    path, _recording = clean_file

    def gaps(handle):
        handle["tod"][0, 10_000:13_000] = np.nan
        handle["tod"][1, 20_000:20_500] = np.nan

    read = read_recording(corrupt(path, tmp_path / "gap.h5", gaps))
    assert read.flags[0, 10_000:13_000].all() and read.flags[1, 20_000:20_500].all()
    assert read.flags.sum() == 3500
    assert np.all(np.isfinite(read.tod))
    result = run(read)
    assert not result["mismatch_found"], result.effect_names
    assert np.isfinite(result["chi2_before"])


def test_nan_pointing_and_hwp_angle_are_masked(clean_file, tmp_path):
    path, recording = clean_file

    def gaps(handle):
        handle["pointings"][1, 500:510, 0] = np.nan
        handle["hwp_angle"][700:705] = np.nan

    read = read_recording(corrupt(path, tmp_path / "nan_pointing.h5", gaps))
    assert read.flags[1, 500:510].all() and not read.flags[0, 500:510].any()
    assert read.flags[:, 700:705].all() and read.flags.sum() == 10 + 2 * 5
    # the HWP angle is bridged over the gap (it turns uniformly)
    difference = read.hwp_angle_rad[695:710] - recording.hwp_angle_rad[695:710]
    assert np.abs(np.angle(np.exp(1j * difference))).max() < 1e-9
    assert np.all(np.isfinite(read.pointings_ecl))


def test_flags_dataset_is_read(clean_file, tmp_path):
    path, _ = clean_file

    def flag(handle):
        flags = np.zeros(handle["tod"].shape, dtype=np.uint8)
        flags[1, 100:200] = 1
        handle.create_dataset("flags", data=flags)
        handle["tod"][1, 150] = np.inf  # Inf in a flagged sample is masked too

    read = read_recording(corrupt(path, tmp_path / "flags.h5", flag))
    assert read.flags[1, 100:200].all() and read.flags.sum() == 100
    assert read.tod[1, 150] == 0.0


def corrupt(source, target, action):
    """A copy of the recording ``source`` at ``target``, edited in place by ``action(handle)``."""
    shutil.copy(source, target)
    with h5py.File(target, "a") as handle:
        action(handle)
    return target


def test_not_hdf5(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("this is not an HDF5 file\n")
    with pytest.raises(RecordingError, match=r"notes\.h5.*not an HDF5 file"):
        read_recording(path)
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.h5")


@pytest.mark.parametrize("dataset", ["tod", "pointings", "hwp_angle"])
def test_missing_dataset(clean_file, tmp_path, dataset):
    path = corrupt(clean_file[0], tmp_path / "missing.h5", lambda h: h.__delitem__(dataset))
    with pytest.raises(RecordingError, match=rf"missing\.h5: missing dataset '{dataset}'"):
        read_recording(path)


def test_length_mismatch(clean_file, tmp_path):
    def shorten(handle):
        hwp = handle["hwp_angle"][()]
        del handle["hwp_angle"]
        handle.create_dataset("hwp_angle", data=hwp[:-10])

    path = corrupt(clean_file[0], tmp_path / "short.h5", shorten)
    with pytest.raises(RecordingError, match=r"short\.h5: length mismatch: 'hwp_angle'"):
        read_recording(path)

    def truncate_pointings(handle):
        pointings = handle["pointings"][()]
        del handle["pointings"]
        handle.create_dataset("pointings", data=pointings[:, :-1])

    path = corrupt(clean_file[0], tmp_path / "short2.h5", truncate_pointings)
    with pytest.raises(RecordingError, match=r"short2\.h5: length mismatch: 'pointings'"):
        read_recording(path)


def test_inf_in_unflagged_samples(clean_file, tmp_path):
    def add_inf(handle):
        tod = handle["tod"][()]
        tod[0, 123] = np.inf
        handle["tod"][...] = tod

    path = corrupt(clean_file[0], tmp_path / "inf.h5", add_inf)
    with pytest.raises(RecordingError, match=r"inf\.h5: 1 Inf value.*'tod'.*sample 123"):
        read_recording(path)


def test_all_nan(clean_file, tmp_path):
    def all_nan(handle):
        handle["tod"][...] = np.full(handle["tod"].shape, np.nan)

    path = corrupt(clean_file[0], tmp_path / "nan.h5", all_nan)
    with pytest.raises(RecordingError, match=r"nan\.h5: no valid sample"):
        read_recording(path)


def test_bad_detector_metadata(clean_file, tmp_path):
    def break_json(handle):
        handle["tod"].attrs["detectors"] = "[{"

    path = corrupt(clean_file[0], tmp_path / "json.h5", break_json)
    with pytest.raises(RecordingError, match=r"json\.h5: attribute 'detectors' is not valid JSON"):
        read_recording(path)


def test_wrong_sky_map_shape(clean_file, tmp_path):
    recording = read_recording(clean_file[0])
    with pytest.raises(SkyMapError, match=r"sky_iqu: sky map of shape \(2, 12288\)"):
        run_with_sky(recording, sky_map()[:2])
    with pytest.raises(SkyMapError, match="not 12 nside"):
        run_with_sky(recording, sky_map()[:, :1000])
    bad = tmp_path / "sky.fits"
    bad.write_text("not a FITS map")
    with pytest.raises(SkyMapError, match=r"sky\.fits: cannot read a sky map"):
        run_with_sky(recording, bad)


def run_with_sky(recording, sky):
    from hwp_tes_systematics.diagnose import diagnose

    return diagnose(recording, sky, A2_K)


def test_recorded_helper_uses_the_file(tmp_path):
    """The tests' recordings go through the file: what diagnose sees was read from disk."""
    recording, injected = recorded(tmp_path, [("crosstalk", {"x": 0.0})], noise_seed=5, hours=0.25)
    assert recording.source.endswith("rec.h5")
    assert injected == [("crosstalk", {"x": 0.0})]


def test_truncated_file_names_the_file_and_what_to_do(clean_file, tmp_path):
    """A copy cut short (interrupted transfer): a RecordingError, not h5py's bare OSError."""
    path = tmp_path / "cut.h5"
    data = clean_file[0].read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match=r"cut\.h5: cannot be read as HDF5.*truncated") as info:
        read_recording(path)
    assert "copy or write it again" in str(info.value)


def test_lab_detector_needs_a2_and_uses_its_own_metadata(clean_file, tmp_path):
    """A channel the instrument model does not know: diagnosed from the file with --a2.

    The file's detectors carry only a name, a polarisation angle and no NET: the noise
    starts from the residual (it is a nominal adjustment anyway), A_2 comes from the caller.
    """
    import json

    from hwp_tes_systematics.diagnose import diagnose
    from hwp_tes_systematics.diagnose.recording import nominal_a2

    def lab(handle):
        detectors = json.loads(handle["tod"].attrs["detectors"])
        handle["tod"].attrs["detectors"] = json.dumps(
            [
                {"name": f"lab{i}", "pol_angle_rad": d["pol_angle_rad"]}
                for i, d in enumerate(detectors)
            ]
        )

    recording = read_recording(corrupt(clean_file[0], tmp_path / "lab.h5", lab))
    assert recording.channel == ""
    with pytest.raises(
        RecordingError, match=r"lab\.h5: channel '' .* not in the instrument model.*--a2"
    ):
        nominal_a2(recording, None, lambda channel: 1.0)
    assert nominal_a2(recording, A2_K, lambda channel: 1.0) == A2_K
    result = diagnose(recording, sky_map(), A2_K, figures=False)
    assert not result["mismatch_found"], (result.effect_names, result["unexplained"])
    net = result["nominal_adjustments"]["lab0"]["noise_net"]
    assert net["value"] == pytest.approx(54.0, rel=0.05)  # the simulated M1-140 NET
