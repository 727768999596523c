"""The command line: python -m hwp_tes_systematics diagnose RECORDING --sky SKY --out DIR.

Run from a temporary folder, not the repository: the embedded default configuration and
its HWP curve tables come with the package."""

import json

import pytest
from helpers import run_cli

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose import simulate_recording, write_recording
from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, sky_map

pytestmark = pytest.mark.slow


def cli(cwd, *arguments):
    """``python -m hwp_tes_systematics diagnose ARGUMENTS`` run in the folder ``cwd``."""
    return run_cli(cwd, "diagnose", *arguments)


def test_cli_finds_an_untold_nonlinearity(tmp_path):
    recording = simulate_recording(
        CHANNEL, 0.5, MASTER_SEED, 4242, sky_map(), A2_K, [("tes_nonlinearity", {"g1": -0.03})]
    )
    write_recording(tmp_path / "rec.h5", recording)
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    assert not (tmp_path / "config").exists()  # no repository configuration here
    result = cli(tmp_path, "rec.h5", "--sky", "sky.fits", "--out", "out")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "mismatch found: tes_nonlinearity" in result.stdout
    diagnosis = json.loads((tmp_path / "out/diagnosis.json").read_text())
    assert diagnosis["mismatch_found"] and diagnosis["effects"][0]["name"] == "tes_nonlinearity"
    assert diagnosis["chi2_after"] < diagnosis["chi2_before"]
    assert (tmp_path / "out/diagnosis.md").exists()
    assert (tmp_path / "out/residual_spectrum.png").stat().st_size > 10_000
    # g1 = -0.03 against the shipped one-year requirement: said in one sentence, printed,
    # in the report and in the JSON
    check = diagnosis["requirement_check"]
    assert check["effect"] == "tes_nonlinearity" and len(check["detectors"]) == 2
    assert all(15 < d["g1_over_requirement"] < 30 for d in check["detectors"])  # 0.03 / 1.47e-3
    assert check["sentence"] in result.stdout
    assert check["sentence"] in (tmp_path / "out/diagnosis.md").read_text()


def test_cli_compares_with_a_given_requirement(tmp_path):
    """--requirement: a run's requirement.json instead of the shipped one; a bad one stops
    before the diagnosis, naming the file."""
    recording = simulate_recording(
        CHANNEL, 0.5, MASTER_SEED, 4244, sky_map(), A2_K, [("tes_nonlinearity", {"g1": -0.03})]
    )
    write_recording(tmp_path / "rec.h5", recording)
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    (tmp_path / "requirement.json").write_text(
        json.dumps({"headline": {"requirement_sigma_g1_per_k": 0.06}, "delta_r_budget": 1e-5})
    )
    result = cli(
        tmp_path, "rec.h5", "--sky", "sky.fits", "--out", "out", "--requirement", "requirement.json"
    )
    assert result.returncode == 0, result.stderr[-3000:]
    check = json.loads((tmp_path / "out/diagnosis.json").read_text())["requirement_check"]
    assert check["requirement"]["source"] == "requirement.json"
    assert all(0.3 < d["g1_over_requirement"] < 0.7 for d in check["detectors"])
    (tmp_path / "bad.json").write_text("{}")
    result = cli(
        tmp_path, "rec.h5", "--sky", "sky.fits", "--out", "out2", "--requirement", "bad.json"
    )
    assert result.returncode == 2 and "bad.json: no headline" in result.stderr
    assert not (tmp_path / "out2").exists()


def test_cli_bad_input_names_the_file(tmp_path):
    not_hdf5 = tmp_path / "notes.h5"
    not_hdf5.write_text("this is not an HDF5 file")
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    result = cli(tmp_path, not_hdf5, "--sky", tmp_path / "sky.fits", "--out", tmp_path / "out")
    assert result.returncode == 2
    assert "notes.h5" in result.stderr and "HDF5" in result.stderr
    assert not (tmp_path / "out/diagnosis.json").exists()


def test_cli_a2_for_a_lab_detector(tmp_path):
    """A recording whose channel the instrument model does not know needs --a2: without it
    the error says so, a negative --a2 is refused, both before anything is written."""
    import h5py

    recording = simulate_recording(CHANNEL, 0.05, MASTER_SEED, 4243, sky_map(), A2_K, [])
    write_recording(tmp_path / "lab.h5", recording)
    with h5py.File(tmp_path / "lab.h5", "r+") as handle:
        detectors = json.loads(handle["tod"].attrs["detectors"])
        handle["tod"].attrs["detectors"] = json.dumps(
            [
                {"name": f"lab{i}", "pol_angle_rad": d["pol_angle_rad"]}
                for i, d in enumerate(detectors)
            ]
        )
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    missing = cli(tmp_path, "lab.h5", "--sky", "sky.fits", "--out", "out")
    assert missing.returncode == 2
    assert "lab.h5" in missing.stderr and "--a2" in missing.stderr
    negative = cli(tmp_path, "lab.h5", "--sky", "sky.fits", "--out", "out", "--a2", "-0.1")
    assert negative.returncode == 2 and "expected an amplitude >= 0" in negative.stderr
    assert not (tmp_path / "out").exists()


def test_cli_diagnoses_a_recording_too_long_for_the_budget_in_segments(tmp_path):
    """--memory-gb below what the recording needs at once: the command cuts it into
    segments that fit, diagnoses each, and reports them combined (--segment-hours asks
    for segments directly)."""
    from hwp_tes_systematics.diagnose.recording_checks import diagnosis_memory_bytes

    recording = simulate_recording(
        CHANNEL, 2.2, MASTER_SEED, 4246, sky_map(), A2_K, [("tes_nonlinearity", {"g1": -0.03})]
    )
    write_recording(tmp_path / "rec.h5", recording)
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    half = diagnosis_memory_bytes(2, recording.n_samples // 2 + 1) / 2**30
    result = cli(
        tmp_path, "rec.h5", "--sky", "sky.fits", "--out", "out", "--memory-gb", f"{half:.6f}"
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "diagnosed in 2 segments" in result.stdout
    diagnosis = json.loads((tmp_path / "out/diagnosis.json").read_text())
    assert [s["effects"] for s in diagnosis["segments"]] == [["tes_nonlinearity"]] * 2
    assert diagnosis["effects"][0]["segments"] == [0, 1]
    assert (tmp_path / "out/segments/1/residual_spectrum.png").exists()
    short = simulate_recording(CHANNEL, 0.5, MASTER_SEED, 4247, sky_map(), A2_K)
    write_recording(tmp_path / "short.h5", short)
    result = cli(
        tmp_path, "short.h5", "--sky", "sky.fits", "--out", "out2", "--segment-hours", "0.25"
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "no mismatch found" in result.stdout
    assert len(json.loads((tmp_path / "out2/diagnosis.json").read_text())["segments"]) == 2
