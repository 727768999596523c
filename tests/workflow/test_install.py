"""The package works outside the repository.

The embedded default configuration and the HWP curve tables it names ship with the
package (``src/hwp_tes_systematics/data/config/``, symlinks to ``config/``), and relative
paths in a configuration resolve from any folder (``config.resolve_path``).
"""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

from hwp_tes_systematics import sky
from hwp_tes_systematics.config import (
    data_path,
    default_config_path,
    load_config,
    resolve_path,
    telescope_optics,
)
from hwp_tes_systematics.instrument.hwp_power import read_hwp_curves

# Files of config/ that the package ships, under the same relative paths below data/.
SHIPPED = ["config/config.yaml", "config/hwp/mft_hwp_curves.csv", "config/hwp/hft_hwp_curves.csv"]
# The one-year requirement a diagnosed nonlinearity is compared with: data/ name -> source.
SHIPPED_REQUIREMENT = (
    "one_year_requirement.json",
    "docs/one_year/recovered_power/requirement.json",
)
PACKAGE_DATA = Path("src/hwp_tes_systematics/data")


def test_package_data_are_symlinks_to_the_repository_config(repo):
    """The shipped copies cannot drift: in the repository they are symlinks to config/."""
    for name in SHIPPED:
        shipped = repo / PACKAGE_DATA / name
        assert shipped.is_symlink(), f"{shipped} should be a symlink to {name}"
        assert shipped.resolve() == (repo / name).resolve()
    assert default_config_path() == data_path() / "config/config.yaml"
    shipped, source = SHIPPED_REQUIREMENT
    assert (repo / PACKAGE_DATA / shipped).is_symlink()
    assert (repo / PACKAGE_DATA / shipped).resolve() == (repo / source).resolve()


def test_default_config_loads_from_another_folder(repo, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = load_config(default_config_path())
    for telescope in ("MFT", "HFT"):
        written = config["optics"]["telescopes"][telescope]["hwp_curves_csv"]
        assert not Path(written).is_absolute() and not Path(written).exists()
        assert resolve_path(written) == data_path() / written
        curves, _, _ = telescope_optics(config, telescope)
        expected = read_hwp_curves(repo / written)
        np.testing.assert_array_equal(curves.freqs_ghz, expected.freqs_ghz)
        np.testing.assert_array_equal(curves.absorption_inductive, expected.absorption_inductive)
        assert curves.absorption_inductive.max() > 0  # the table, not an ideal HWP


def test_relative_path_in_the_current_folder_comes_first(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    local = Path("config/hwp/mft_hwp_curves.csv")
    local.parent.mkdir(parents=True)
    local.write_text(
        "freq_ghz,absorption_capacitive,absorption_inductive,"
        "transmission_capacitive,transmission_inductive\n"
        "50,0.01,0.02,0.9,0.9\n"
        "500,0.01,0.02,0.9,0.9\n"
    )
    assert resolve_path(local) == local
    curves, _, _ = telescope_optics(load_config(default_config_path()), "MFT")
    assert curves.freqs_ghz.tolist() == [50.0, 500.0]


def test_path_found_nowhere_is_returned_as_written(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert resolve_path("config/hwp/missing.csv") == Path("config/hwp/missing.csv")
    absolute = tmp_path / "elsewhere.csv"
    assert resolve_path(absolute) == absolute


def test_cli_help_from_another_folder(tmp_path):
    result = run_cli(tmp_path, "diagnose", "--help")
    assert result.returncode == 0, result.stderr
    assert "embedded default" in result.stdout


@pytest.mark.slow
def test_cli_merges_config_over_the_shipped_default_from_another_folder(tmp_path):
    """From a folder without config/, the default is found and --config merged over it
    (checked with the other arguments, before the recording is read)."""
    (tmp_path / "cold_tc.yaml").write_text("tes:\n  tc_k: 0.05\n")
    (tmp_path / "recording.h5").write_bytes(b"")  # never read: the configuration stops first
    sky.write_sky_map(tmp_path / "sky.fits", np.zeros((3, 12)))  # its headers are checked
    result = run_cli(
        tmp_path,
        "diagnose",
        "recording.h5",
        "--sky",
        "sky.fits",
        "--config",
        "cold_tc.yaml",
        "--out",
        "out",
    )
    assert result.returncode == 2
    # the message names the default, then the override, and compares a default key
    # (tes.tbath_k) with the overridden one: both files were read and merged
    assert f"{default_config_path()} + cold_tc.yaml" in result.stderr, result.stderr
    assert "must be below tes.tc_k = 0.05" in result.stderr, result.stderr


def test_built_package_ships_the_default_config_and_curve_tables(repo, tmp_path):
    """setuptools copies the symlinks' targets into the build, as into a wheel."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(repo / name, source / name)
    shutil.copytree(repo / "config", source / "config")
    (source / SHIPPED_REQUIREMENT[1]).parent.mkdir(parents=True)
    shutil.copy(repo / SHIPPED_REQUIREMENT[1], source / SHIPPED_REQUIREMENT[1])
    shutil.copytree(
        repo / "src",
        source / "src",
        symlinks=True,
        ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"),
    )
    build = subprocess.run(
        [sys.executable, "-c", "import setuptools; setuptools.setup()", "build_py"]
        + ["--build-lib", str(tmp_path / "lib")],
        cwd=source,
        check=False,
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    data = tmp_path / "lib/hwp_tes_systematics/data"
    assert (data / "config.schema.yaml").is_file()
    for name in SHIPPED:
        built = data / name
        assert built.is_file() and not built.is_symlink(), f"{name} missing from the build"
        assert built.read_bytes() == (source / name).read_bytes()
    built = data / SHIPPED_REQUIREMENT[0]
    assert built.is_file() and not built.is_symlink(), "the one-year requirement is missing"
    assert built.read_bytes() == (source / SHIPPED_REQUIREMENT[1]).read_bytes()
