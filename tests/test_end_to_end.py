"""The whole DAG on a tiny configuration, in a temporary directory."""

import json

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def test_whole_workflow_on_tiny_config(tiny_local_run):
    workdir, result = tiny_local_run  # shared with tests/test_slurm.py
    assert result.returncode == 0, result.stderr[-4000:]
    requirement = json.loads((workdir / "results/requirement.json").read_text())
    assert np.isfinite(requirement["requirement_sigma_g1_per_k"])
    assert requirement["requirement_sigma_g1_per_k"] > 0
    assert np.isfinite(requirement["quadratic_fit"]["k_per_k2"])
    assert np.isfinite(requirement["power_law_fit"]["exponent"])
    assert [row["sigma_g1_per_k"] for row in requirement["per_sigma"]] == [1e-3, 1e-1]
    assert requirement["n_seeds"] == 2 and len(requirement["config_sha256"]) == 64
    figures = sorted(p.name for p in (workdir / "results/figures").glob("*.png"))
    for number in range(1, 9):
        assert any(name.startswith(f"fig{number}_") for name in figures), figures
    # every rule wrote its log
    for rule in (
        "hwp_power",
        "kw_conversion",
        "tes_response",
        "foreground_maps",
        "tod_figures",
        "notch_effect",
        "noise_model",
        "requirement",
    ):
        assert (workdir / f"logs/{rule}.log").exists(), rule
