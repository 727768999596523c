"""Rule-level tests: the HWP-power, K/W and TES rules on the default config in a temp dir."""

import pandas as pd
import pytest
from helpers import make_workdir, snakemake

pytestmark = pytest.mark.slow


def test_hwp_power_kw_and_tes_rules(repo, tmp_path):
    workdir = make_workdir(repo, tmp_path)
    result = snakemake(
        workdir,
        "results/inputs/hwp_power.csv",
        "results/inputs/kw_conversion.csv",
        "results/inputs/tes_response.csv",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    hwp = pd.read_csv(workdir / "results/inputs/hwp_power.csv")
    kw = pd.read_csv(workdir / "results/inputs/kw_conversion.csv")
    tes = pd.read_csv(workdir / "results/inputs/tes_response.csv")
    assert len(hwp) == len(kw) == len(tes) == 22
    assert (kw["kelvin_per_watt"] > 0).all() and kw["kelvin_per_watt"].notna().all()
    # C from the 1 mK finite step agrees with 1/(dP/dT) to ~ delta T / T
    assert ((kw["kelvin_per_watt"] / kw["kelvin_per_watt_analytic"] - 1).abs() < 2e-3).all()
    mhft = kw["telescope"] != "LFT"
    assert (kw.loc[mhft, "a2_k_cmb"] > 0).all() and (kw.loc[~mhft, "a2_k_cmb"] == 0).all()
    assert (tes["g1_per_k"] < 0).all()  # responsivity magnitude falls with load
    for figure in (
        "fig1_hwp_absorption_transmission",
        "fig2_hwp_differential_power",
        "fig3_hwp_emission_vs_sky",
        "fig4_tes_response",
    ):
        assert (workdir / f"results/figures/{figure}.png").stat().st_size > 10_000


def test_malformed_curve_table_fails_cleanly(repo, tmp_path):
    workdir = make_workdir(repo, tmp_path)
    (workdir / "config/hwp/mft_hwp_curves.csv").write_text("freq_ghz,absorption_capacitive\n1,2\n")
    result = snakemake(workdir, "results/inputs/hwp_power.csv")
    assert result.returncode != 0
    assert "mft_hwp_curves.csv" in result.stderr and "missing column" in result.stderr
    assert not (workdir / "results/inputs/hwp_power.csv").exists()
    leftovers = list((workdir / "results").rglob("*")) if (workdir / "results").exists() else []
    assert not [p for p in leftovers if p.is_file()], leftovers


@pytest.mark.parametrize(
    "override, message",
    [
        ("instrument:\n  systematics_channels: [M1-999]\n", "M1-999"),
        ("tes:\n  tbath_kelvin: 0.1\n", "tbath_kelvin"),
        ("optics:\n  t_cmb_k: -2.7\n", "optics.t_cmb_k"),
    ],
)
def test_bad_config_stops_before_any_job(repo, tmp_path, override, message):
    workdir = make_workdir(repo, tmp_path)
    (workdir / "bad.yaml").write_text(override)
    result = snakemake(workdir, extra=("--configfile", "bad.yaml"))
    assert result.returncode != 0
    assert message in result.stderr + result.stdout
    assert not (workdir / "results").exists()
