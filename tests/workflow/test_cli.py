"""The command line itself: its name (the console script's or ``python -m``), --version,
each command's help (description, outputs, example), arguments and output paths checked
before any work, progress on stderr (-q, -v), and the verdict's ratios to two significant
figures. Fast: the diagnosis is replaced where only the command line is tested, and the
one real diagnosis is of a 72 s recording."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hwp_tes_systematics import __version__, cli
from hwp_tes_systematics.diagnose.bound.requirement_check import (
    bound_nonlinearity,
    compare_nonlinearity,
    load_requirement,
    significant,
)

SCRIPT = Path(sys.executable).with_name("hwp-tes-systematics")  # [project.scripts]


@pytest.fixture(autouse=True)
def logging_restored():
    """main() configures logging as a process would: put it back after each test."""
    root, package = logging.getLogger(), logging.getLogger("hwp_tes_systematics")
    handlers, levels = list(root.handlers), (root.level, package.level)
    yield
    root.handlers[:] = handlers
    root.setLevel(levels[0])
    package.setLevel(levels[1])


@pytest.fixture
def inputs(tmp_path):
    """A recording file that exists (its content is not read in these tests) and a sky map
    (a tiny HEALPix I, Q, U FITS file: its headers are checked before the work)."""
    import numpy as np

    from hwp_tes_systematics import sky

    (tmp_path / "rec.h5").write_bytes(b"")
    sky.write_sky_map(tmp_path / "sky.fits", np.zeros((3, 12)))
    return tmp_path


class Result(dict):
    requirement_sentence = "Fitted g1 = ... times the requirement."


@pytest.fixture
def no_work(monkeypatch):
    """run_diagnose replaced: fails the test if called (checks must come before the work)."""

    def fail(*args, **kwargs):
        pytest.fail("the diagnosis started before the arguments were checked")

    monkeypatch.setattr(cli, "run_diagnose", fail)


def exit_status(capsys, *argv, prog="hwp-tes-systematics"):
    """(status, stdout, stderr) of main(argv); argparse's exits included."""
    try:
        status = cli.main([str(a) for a in argv], prog=prog)
    except SystemExit as exit:
        status = exit.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_version(capsys):
    status, out, _ = exit_status(capsys, "--version")
    assert status == 0 and out.strip() == f"hwp-tes-systematics {__version__}"


def test_the_console_script_names_itself_and_python_m_its_module():
    if not SCRIPT.exists():
        pytest.skip(f"{SCRIPT}: the console script is not installed (pip install -e .)")
    script = subprocess.run(
        [SCRIPT, "diagnose", "--help"], capture_output=True, text=True, check=True
    ).stdout
    assert script.startswith("usage: hwp-tes-systematics diagnose")
    assert "python -m" not in script
    assert "  hwp-tes-systematics diagnose recording.h5 --sky sky.fits --out" in script
    version = subprocess.run([SCRIPT, "--version"], capture_output=True, text=True, check=True)
    assert version.stdout.strip() == f"hwp-tes-systematics {__version__}"
    module = subprocess.run(
        [sys.executable, "-m", "hwp_tes_systematics", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert module.startswith("usage: python -m hwp_tes_systematics")


def test_top_level_help_names_the_program_as_run(capsys):
    status, out, _ = exit_status(capsys, "--help")
    assert status == 0 and out.startswith("usage: hwp-tes-systematics [-h] [--version]")
    assert "python -m" not in out
    assert "diagnose RECORDING.h5 --sky SKY.fits" in out  # the commands' summary
    assert "example:\n  hwp-tes-systematics diagnose recording.h5 --sky sky.fits" in out
    status, out, _ = exit_status(capsys, "--help", prog=cli.MODULE_PROG)
    assert out.startswith("usage: python -m hwp_tes_systematics [-h] [--version]")


def test_program_name_from_argv0():
    assert cli.program_name("/venv/bin/hwp-tes-systematics") == "hwp-tes-systematics"
    assert cli.program_name("/src/hwp_tes_systematics/__main__.py") == cli.MODULE_PROG


def test_diagnose_help_has_a_description_the_outputs_and_an_example(capsys):
    status, out, _ = exit_status(capsys, "diagnose", "--help")
    assert status == 0
    assert "Diagnose one recording against its simulation" in out
    for output in ("diagnosis.json", "diagnosis.md", "residual_*.png", "segments/<i>/"):
        assert output in out, output
    assert "example:\n  hwp-tes-systematics diagnose recording.h5 --sky sky.fits" in out
    assert "-q, --quiet" in out and "-v, --verbose" in out


@pytest.mark.parametrize("command", ["config-reference", "effect-catalog", "figure8"])
def test_every_command_help_has_a_description_and_an_example(capsys, command):
    status, out, _ = exit_status(capsys, command, "--help")
    assert status == 0
    description = out.split("\n\n")[1]
    assert len(description.split()) >= 10, description
    assert f"example:\n  hwp-tes-systematics {command}" in out


def test_unwritable_out_fails_at_once_naming_out(capsys, inputs, no_work):
    """--out under a file, --out an existing file, --out in a folder that cannot be
    written: exit 2 before any work, the message naming --out, the path and what was
    expected; nothing created."""
    (inputs / "file").write_text("")
    unwritable = inputs / "locked"
    unwritable.mkdir()
    unwritable.chmod(0o500)
    cases = [
        (inputs / "file" / "out", "is a file, not a folder"),
        (inputs / "file", "exists and is not a folder"),
    ]
    if os.geteuid() != 0:  # root writes anywhere: a read-only folder stops only others
        cases.append((unwritable / "out", "is not writable"))
    elif Path("/proc").is_dir():  # root: a folder nobody can create files in
        cases.append((Path("/proc/hwp_tes_out"), "is not writable"))
    try:
        for out, expected in cases:
            status, _, err = exit_status(
                capsys, "diagnose", inputs / "rec.h5", "--sky", inputs / "sky.fits", "--out", out
            )
            assert status == 2, (out, err)
            assert f"error: argument --out: {out}" in err and expected in err, err
            assert "expected" in err
        assert not (inputs / "locked" / "out").exists()
    finally:
        unwritable.chmod(0o700)


def test_figure8_out_is_checked_first(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(cli, "redraw_figure8", lambda *a: pytest.fail("redrew"))
    (tmp_path / "file").write_text("")
    requirement = tmp_path / "requirement.json"
    requirement.write_text("{}")
    (tmp_path / "delta_r.csv").write_text("")
    status, _, err = exit_status(
        capsys, "figure8", requirement, "--out", tmp_path / "file" / "fig8.png"
    )
    assert status == 2 and "argument --out:" in err and "is a file, not a folder" in err
    status, _, err = exit_status(capsys, "figure8", requirement, "--out", tmp_path)
    assert status == 2 and f"argument --out: {tmp_path} is a folder" in err


@pytest.mark.parametrize(
    "option, value, expected",
    [
        ("--a2", "-0.1", "expected an amplitude >= 0 in K_CMB"),
        ("--a2", "nan", "expected an amplitude >= 0 in K_CMB"),
        ("--memory-gb", "0", "expected a memory > 0 GiB"),
        ("--segment-hours", "inf", "expected a duration > 0 h"),
        ("--segment-hours", "six", "expected a duration > 0 h"),
        ("--delta-bic", "5", "expected a BIC change <= 0"),
        ("--config", "missing.yaml", "missing.yaml: no such file (expected a file)"),
        ("--sky", "missing.fits", "missing.fits: no such file (expected a file)"),
    ],
)
def test_bad_arguments_name_the_option(capsys, inputs, no_work, option, value, expected):
    arguments = {"--sky": inputs / "sky.fits", "--out": inputs / "out", option: value}
    flat = [str(part) for item in arguments.items() for part in item]
    status, _, err = exit_status(capsys, "diagnose", inputs / "rec.h5", *flat)
    assert status == 2
    assert f"argument {option}: " in err and expected in err, err
    assert not (inputs / "out").exists()


def test_a_sky_that_is_not_a_map_stops_before_the_work(capsys, inputs, no_work):
    from astropy.io import fits

    (inputs / "notes.fits").write_text("not FITS")
    fits.PrimaryHDU().writeto(inputs / "image.fits")
    for name, expected in (("notes.fits", "not a FITS file"), ("image.fits", "tables: []")):
        status, _, err = exit_status(
            capsys, "diagnose", inputs / "rec.h5", "--sky", inputs / name,
            "--out", inputs / "out",
        )  # fmt: skip
        assert status == 2 and f"argument --sky: {inputs / name}: " in err, err
        assert expected in err and "expected a HEALPix I, Q, U map" in err, err


def test_missing_recording_and_bad_requirement_stop_before_the_work(capsys, inputs, no_work):
    common = ["--sky", inputs / "sky.fits", "--out", inputs / "out"]
    status, _, err = exit_status(capsys, "diagnose", inputs / "none.h5", *common)
    assert status == 2 and "argument recording: " in err and "none.h5: no such file" in err
    (inputs / "bad.json").write_text("{}")
    status, _, err = exit_status(
        capsys, "diagnose", inputs / "rec.h5", *common, "--requirement", inputs / "bad.json"
    )
    assert status == 2 and "argument --requirement: " in err and "bad.json: no headline" in err
    assert not (inputs / "out").exists()


def fake_diagnosis(*args, **kwargs):
    """What run_diagnose logs on its way (a stage at INFO, a detail at DEBUG), and a result."""
    logging.getLogger("hwp_tes_systematics.diagnose.pipeline").info("STAGE selecting effects")
    logging.getLogger("hwp_tes_systematics.diagnose.pipeline").debug("DETAIL selected: none")
    logging.getLogger("matplotlib").info("OTHER a library's line")
    return Result(mismatch_found=False, chi2_before=12.0)


@pytest.mark.parametrize(
    "flags, shown, hidden",
    [
        ([], ["STAGE"], ["DETAIL", "OTHER"]),
        (["-q"], [], ["STAGE", "DETAIL"]),
        (["-v"], ["STAGE", "DETAIL"], []),
    ],
)
def test_progress_on_stderr_quiet_and_verbose(capsys, inputs, monkeypatch, flags, shown, hidden):
    monkeypatch.setattr(cli, "run_diagnose", fake_diagnosis)
    status, out, err = exit_status(
        capsys, "diagnose", inputs / "rec.h5", "--sky", inputs / "sky.fits",
        "--out", inputs / "out", *flags,
    )  # fmt: skip
    assert status == 0 and "no mismatch found (chi2 12.0)" in out
    for text in shown:
        assert text in err, (flags, err)
    for text in hidden:
        assert text not in err, (flags, err)


def test_a_real_diagnosis_shows_its_stages(capsys, tmp_path):
    """The pipeline's stages reach stderr by default, with the time since the start."""
    from hwp_tes_systematics import sky
    from hwp_tes_systematics.diagnose import simulate_recording, write_recording
    from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, sky_map

    write_recording(
        tmp_path / "rec.h5", simulate_recording(CHANNEL, 0.02, MASTER_SEED, 5, sky_map(), A2_K)
    )
    sky.write_sky_map(tmp_path / "sky.fits", sky_map())
    status, _, err = exit_status(
        capsys, "diagnose", tmp_path / "rec.h5", "--sky", tmp_path / "sky.fits",
        "--out", tmp_path / "out",
    )  # fmt: skip
    assert status == 0, err
    for stage in (
        "nominal model (2 detectors x 2232 samples",
        "fitting the nominal adjustments",
        "locating where the residual differs from noise",
        "selecting effects (pass 1)",
        "looking for unexplained structure",
        "writing the report and figures",
        "done:",
    ):
        assert stage in err, (stage, err)
    assert " s] done:" in err
    assert json.loads((tmp_path / "out/diagnosis.json").read_text())["chi2_before"] > 0


def test_significant_keeps_two_figures():
    assert significant(4.98e-3 / 4.9e-3) == "1.0"  # format(.., ".2g") gives "1"
    assert significant(12.3) == "12" and significant(0.0123) == "0.012"
    assert significant(5.0) == "5.0" and significant(123.0) == "120"
    assert significant(189.0) == "190" and significant(2.5e7) == "2.5e+07"
    assert significant(0.999) == "1.0" and significant(9.96, 3) == "9.96"


def test_verdict_ratios_have_two_significant_figures():
    """g1 = 4.98e-3 against sigma_g1 < 4.9e-3 is "1.0 times the requirement", not "1"."""
    requirement = dict(load_requirement(), sigma_g1_per_k=4.9e-3)

    def entries(*values):
        return {
            f"g1[d{k}]": {"parameter": "g1", "detector": f"d{k}", "value": v, "sigma": 2e-3}
            for k, v in enumerate(values)
        }

    sentence = compare_nonlinearity({"parameters": entries(4.98e-3)}, requirement)["sentence"]
    assert "|g1| is 1.0 times the requirement." in sentence
    assert "this recording knows g1 2.4 times better than required" in sentence
    loose = compare_nonlinearity(
        {"parameters": entries(4.98e-3)}, dict(requirement, sigma_g1_per_k=2e-3)
    )
    assert "knows g1 only to 1.0 times the requirement" in loose["sentence"]
    sentence = compare_nonlinearity({"parameters": entries(-4.9e-3, 9.8e-3)}, requirement)
    assert "|g1| is 1.0-2.0 times the requirement." in sentence["sentence"]
    bound = bound_nonlinearity(entries(0.98e-3 - 4e-3, 0.0), requirement, -1.0)["sentence"]
    assert "cannot show |g1| below the requirement (its bound is 0.82-1.4 times it)" in bound


def test_a_bad_configuration_stops_before_the_work(capsys, inputs, no_work):
    (inputs / "cold.yaml").write_text("tes:\n  tc_k: 0.05\n")
    status, _, err = exit_status(
        capsys, "diagnose", inputs / "rec.h5", "--sky", inputs / "sky.fits",
        "--config", inputs / "cold.yaml", "--out", inputs / "out",
    )  # fmt: skip
    assert status == 2 and "cold.yaml" in err and "must be below tes.tc_k = 0.05" in err, err
    assert not (inputs / "out").exists()


def test_segments_show_the_time_left(tmp_path, monkeypatch, caplog):
    """A recording diagnosed in segments logs each segment with the time elapsed and an
    estimate of the time left (equal segments: the mean so far times those to go). The
    diagnosis of a segment is replaced by one that takes a minute on a fake clock."""
    from types import SimpleNamespace

    from hwp_tes_systematics.diagnose import segments, simulate_recording, write_recording
    from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, sky_map

    path = tmp_path / "rec.h5"
    write_recording(path, simulate_recording(CHANNEL, 0.02, MASTER_SEED, 6, sky_map(), A2_K))
    clock = iter([0, 0, 60, 120])  # the start, then each segment's: a minute apiece
    monkeypatch.setattr(segments, "time", SimpleNamespace(monotonic=lambda: next(clock)))
    monkeypatch.setattr(segments, "diagnose", lambda *a, **k: SimpleNamespace(to_dict=dict))
    monkeypatch.setattr(segments, "combine_segments", lambda *a: {"recording": {}})
    caplog.set_level(logging.INFO, logger="hwp_tes_systematics")
    segments.diagnose_segments(path, sky_map(), A2_K, segment_hours=0.02 / 3)  # 3 x 24 s
    lines = [r.getMessage() for r in caplog.records if "segment" in r.getMessage()]
    assert len(lines) == 3, lines
    assert lines[0].endswith("segment 1 of 3, 0.00-0.01 h")
    assert lines[1].endswith("segment 2 of 3, 0.01-0.01 h (elapsed 1.0 min, ~2.0 min left)")
    assert lines[2].endswith("(elapsed 2.0 min, ~1.0 min left)")
