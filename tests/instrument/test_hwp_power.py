"""HWP power tables: physics of the per-axis emission and the curve-table reader."""

import numpy as np
import pandas as pd
import pytest
from scipy.constants import k

from hwp_tes_systematics.instrument.channels import Channel
from hwp_tes_systematics.instrument.hwp_power import (
    HwpCurveError,
    HwpCurves,
    OpticalElement,
    assumed_metal_mesh_curves,
    downstream_efficiency,
    hwp_power_for_channel,
    read_hwp_curves,
)

HEADER = (
    "freq_ghz,absorption_capacitive,absorption_inductive,transmission_capacitive,"
    "transmission_inductive\n"
)
CHAIN = [
    OpticalElement("lens", 5.0, 0.0, 0.8),
    OpticalElement("detector", 0.1, 0.0, 0.5),
]


def make_channel(center_ghz=2.0, width_ghz=0.4):
    freqs = np.linspace(center_ghz - width_ghz, center_ghz + width_ghz, 9)
    weights = (np.abs(freqs - center_ghz) <= width_ghz / 2).astype(float)
    return Channel(
        "T-002",
        "MFT",
        center_ghz,
        width_ghz,
        freqs,
        weights,
        50.0,
        20.0,
        0.01,
        1.0,
        30.0,
        31.0,
        39.0,
        2,
        ("a", "b"),
    )


def flat_curves(a_cap, a_ind, t_cap, t_ind):
    freqs = np.array([0.1, 1000.0])
    return HwpCurves(
        freqs,
        np.full(2, a_cap),
        np.full(2, a_ind),
        np.full(2, t_cap),
        np.full(2, t_ind),
        source="flat",
    )


def test_gray_body_emission_in_rayleigh_jeans_limit():
    """Flat absorption a, RJ band: P_emis = a k T_HWP Delta nu eta_down."""
    channel = make_channel()
    curves = flat_curves(0.03, 0.01, 0.9, 0.9)
    row = hwp_power_for_channel(channel, curves, 20.0, CHAIN, incoming_load_temperature_k=2.725)
    eta = downstream_efficiency(CHAIN)
    assert eta == pytest.approx(0.4)
    for a, axis in ((0.03, "capacitive"), (0.01, "inductive")):
        expected = a * k * 20.0 * 0.4e9 * eta
        assert row[f"p_emission_{axis}_w"] == pytest.approx(expected, rel=1e-3)
    assert row["delta_p_transmission_w"] == pytest.approx(0.0, abs=1e-30)
    assert row["a2_w"] == pytest.approx(row["delta_p_emission_w"])


def test_differential_transmission_of_the_incoming_load():
    channel = make_channel()
    curves = flat_curves(0.0, 0.0, 0.95, 0.90)
    row = hwp_power_for_channel(
        channel, curves, 20.0, CHAIN, incoming_load_temperature_k=300.0, a2_over_delta_p=0.5
    )
    expected = 0.05 * k * 300.0 * 0.4e9 * 0.4
    assert row["delta_p_transmission_w"] == pytest.approx(expected, rel=1e-3)
    assert row["a2_w"] == pytest.approx(0.5 * expected, rel=1e-3)


def test_ideal_hwp_has_no_synchronous_signal():
    row = hwp_power_for_channel(make_channel(), HwpCurves.ideal(), 20.0, CHAIN, 2.725)
    assert row["a2_w"] == 0.0
    assert row["p_emission_capacitive_w"] == 0.0


def test_shipped_assumed_curves_are_reproducible(repo):
    """The shipped assumption tables equal their documented generator."""
    for telescope in ("MFT", "HFT"):
        shipped = pd.read_csv(repo / f"config/hwp/{telescope.lower()}_hwp_curves.csv", comment="#")
        pd.testing.assert_frame_equal(shipped, assumed_metal_mesh_curves(telescope))
        curves = read_hwp_curves(repo / f"config/hwp/{telescope.lower()}_hwp_curves.csv")
        assert np.all(curves.absorption_capacitive > curves.absorption_inductive)


@pytest.mark.parametrize(
    "content, message",
    [
        ("freq_ghz,absorption_capacitive\n1,0.1\n", "missing column"),
        (
            HEADER + "1,0.1,0.1,0.9,0.9\n2,abc,0.1,0.9,0.9\n",
            "row 1",
        ),
        (
            HEADER + "2,0.1,0.1,0.9,0.9\n1,0.1,0.1,0.9,0.9\n",
            "strictly increasing",
        ),
        (
            HEADER + "1,0.2,0.1,0.9,0.9\n2,0.2,0.1,0.9,0.9\n",
            "energy conservation",
        ),
    ],
)
def test_malformed_curve_table_names_file_and_problem(tmp_path, content, message):
    path = tmp_path / "bad_curves.csv"
    path.write_text(content)
    with pytest.raises(HwpCurveError, match=message) as error:
        read_hwp_curves(path)
    assert "bad_curves.csv" in str(error.value)


def test_missing_curve_table(tmp_path):
    with pytest.raises(HwpCurveError, match="file not found"):
        read_hwp_curves(tmp_path / "nope.csv")


def test_curves_must_cover_the_band():
    curves = flat_curves(0.01, 0.01, 0.9, 0.9)
    with pytest.raises(HwpCurveError, match="extend the table"):
        curves.on(np.array([2000.0]))
