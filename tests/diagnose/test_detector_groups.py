"""Effects shared by focal-plane groups (wafer, readout line, pixel) beside per-detector ones.

The groups come from the detectors' metadata (:attr:`.recording.Recording.groups`); the
slow tests diagnose TOAST recordings whose gain drift TOAST's own ``GainDrifter`` made,
common to a wafer or each detector its own, and check the scope the report gives.
"""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.recording import detector_groups, read_recording
from hwp_tes_systematics.diagnose.report.diagnosis import parameter_table, scope_sentence
from hwp_tes_systematics.diagnose.testbed import sky_map

A2_K = 0.2  # the HWPSS amplitude added to TOAST's signal [K_CMB] (assumption, MFT-like)


def _detectors(**columns):
    n = len(next(iter(columns.values())))
    return [{"name": f"d{i}", **{k: v[i] for k, v in columns.items()}} for i in range(n)]


def test_groups_are_the_keys_that_split_the_detectors():
    detectors = _detectors(
        wafer=["W0", "W0", "W1", "W1"],
        squid=[3, 3, 7, 7],  # the same split as the wafers: left out
        pixel=[0, 0, 1, 2],
    )
    assert detector_groups(detectors) == {
        "wafer": ("W0", "W0", "W1", "W1"),
        "pixel": ("0", "0", "1", "2"),
    }


@pytest.mark.parametrize(
    "wafer",
    [
        ["W0", "W0", "W0"],  # one group: that is "all detectors"
        ["W0", "W1", "W2"],  # each detector its own: that is "per detector"
        ["W0", None, "W0"],  # a detector without one
    ],
)
def test_no_groups_where_the_key_does_not_split_the_detectors(wafer):
    assert detector_groups(_detectors(wafer=wafer)) == {}


def test_the_report_tables_parameters_per_detector_and_per_group():
    parameters = {
        "g1[a]": {"value": 0.01, "sigma": 0.001, "unit": "1", "detector": "a", "parameter": "g1"},
        "g2[a]": {"value": 0.02, "sigma": None, "unit": "1", "detector": "a", "parameter": "g2"},
        "g1[wafer W0]": {
            "value": 0.03,
            "sigma": 0.002,
            "unit": "1",
            "detector": "wafer W0",
            "parameter": "g1",
        },
    }
    lines = parameter_table(parameters)
    assert lines[0] == "| detector | g1 [1] | g2 [1] |"
    assert lines[2] == "| a | 0.01 +- 0.001 | 0.02 +- - |"
    assert lines[3] == "| wafer W0 | 0.03 +- 0.002 |  |"
    scope = {"by": "wafer", "groups": {"W0": ["a", "b"], "W1": ["c"]}}
    assert scope_sentence(scope, 3) == "one set of parameters per wafer: W0 (a, b), W1 (c)"


@pytest.fixture(scope="module")
def sky_fits(tmp_path_factory):
    path = tmp_path_factory.mktemp("sky") / "sky.fits"
    hp.write_map(path, sky_map(), dtype=np.float64)
    return path


def _diagnosed(tmp_path, sky_fits, mismatch: float, seed: int):
    pytest.importorskip("toast", reason="the toast extra is not installed")
    from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

    truth: dict = {}
    path = write_toast_recording(
        tmp_path,
        sky_fits,
        hours=2.0,
        seed=seed,
        n_pixels=7,
        wafers=2,
        a2_k=A2_K,
        gain_drift_sigma=0.03,
        gain_drift_mode="slow_drift",
        gain_drift_mismatch=mismatch,
        truth=truth,
    )
    recording = read_recording(path)
    assert set(recording.groups) == {"wafer", "pixel"}
    return diagnose(recording, sky_map(), A2_K, figures=False).to_dict(), truth


@pytest.mark.slow
def test_a_drift_common_to_each_wafer_is_named_with_its_scope(tmp_path, sky_fits):
    """TOAST's slow_drift with no part per detector: one drift per wafer (a 1/f stream, not
    a polynomial). Named a gain drift shared per wafer, the wafers' g1 within 3 sigma."""
    result, truth = _diagnosed(tmp_path, sky_fits, mismatch=0.0, seed=5)
    first = result["effects"][0]
    assert first["name"] == "gain_drift"
    assert first["scope"]["by"] == "wafer"
    assert first["scope"]["groups"] == {
        "W0": [f"D{p}{ab}-140" for p in range(4) for ab in "AB"],
        "W1": [f"D{p}{ab}-140" for p in range(4, 7) for ab in "AB"],
    }
    for wafer, detector in (("W0", "D0A-140"), ("W1", "D6A-140")):
        fitted = first["parameters"][f"g1[wafer {wafer}]"]
        expected = truth["gain_drift_legendre"][detector][0]
        assert abs(fitted["value"] - expected) < 3 * fitted["sigma"], (wafer, fitted, expected)


@pytest.mark.slow
def test_a_drift_of_each_detector_is_named_per_detector(tmp_path, sky_fits):
    """TOAST's slow_drift, each detector its own stream: a gain drift per detector (not the
    2f-only slow modulation, which has as many parameters but leaves the dipole's drift)."""
    result, _ = _diagnosed(tmp_path, sky_fits, mismatch=1.0, seed=7)
    first = result["effects"][0]
    assert first["name"] == "gain_drift"
    assert first["scope"]["by"] == "detector"
    assert "hwpss_slow_modulation" not in {e["name"] for e in result["effects"]}


@pytest.mark.slow
@pytest.mark.parametrize("coupling", [0.05, 0.0])
def test_toasts_crosstalk_is_found_in_the_pair_it_couples(tmp_path, sky_fits, coupling):
    """TOAST's CrossTalk, 5 % of D0A's TOD into D0B, one hour: the residuals' correlation
    names the pair, x within 3 sigma of c; without it, nothing is named."""
    pytest.importorskip("toast", reason="the toast extra is not installed")
    from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

    path = write_toast_recording(
        tmp_path,
        sky_fits,
        hours=1.0,
        seed=4,
        a2_k=A2_K,
        crosstalk={(1, 0): coupling} if coupling else None,
    )
    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    found = {e["name"]: e for e in result["effects"]}
    if not coupling:
        assert "detector_crosstalk" not in found
        return
    x = found["detector_crosstalk"]["parameters"]["x[D0A-140-D0B-140]"]
    assert abs(x["value"] - coupling) < 3 * x["sigma"], x
    assert x["sigma"] < coupling / 5


@pytest.mark.slow
def test_crosstalk_among_fourteen_detectors_takes_exactly_the_coupled_pairs(tmp_path, sky_fits):
    """TOAST's CrossTalk, c = 0.03 between three pairs of 14 detectors (one of them
    negative), one hour: exactly those 3 of the 91 pairs are taken."""
    pytest.importorskip("toast", reason="the toast extra is not installed")
    from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

    couplings = {(0, 1): 0.03, (3, 8): 0.03, (12, 2): -0.03}
    path = write_toast_recording(
        tmp_path, sky_fits, hours=1.0, seed=5, n_pixels=7, a2_k=A2_K, crosstalk=couplings
    )
    recording = read_recording(path)
    result = diagnose(recording, sky_map(), A2_K, figures=False).to_dict()
    (entry,) = [e for e in result["effects"] if e["name"] == "detector_crosstalk"]
    names = recording.detector_names
    coupled = {f"{names[min(i, j)]}-{names[max(i, j)]}" for i, j in couplings}
    taken = {p["detector"] for p in entry["parameters"].values() if p["taken"]}
    assert len(entry["parameters"]) == 91
    assert taken == coupled


def test_a_rank_one_pattern_is_a_common_noise_and_chosen_pairs_are_crosstalk():
    """The pairs' correlations x_ij = b_i b_j within two groups (and 0 across) are fitted
    back to b by the rank-one fit of the groups' partition, which beats one group of all;
    two coupled pairs alone are not a rank-one pattern."""
    from types import SimpleNamespace

    from hwp_tes_systematics.diagnose.effects.common_mode import fit_common_mode

    rng = np.random.default_rng(3)
    n_det = 8
    wafer = ["W0"] * 4 + ["W1"] * 4
    ctx = SimpleNamespace(n_detectors=n_det, groups={"wafer": tuple(wafer)})
    b = rng.uniform(0.2, 0.35, n_det)
    pairs = [(i, j) for i in range(n_det) for j in range(i + 1, n_det)]
    sigma = np.full(len(pairs), 0.004)
    same = np.array([wafer[i] == wafer[j] for i, j in pairs])
    pattern = np.array([b[i] * b[j] for i, j in pairs]) * same
    x = pattern + rng.normal(0.0, 0.004, len(pairs))
    common = fit_common_mode(ctx, pairs, x, sigma, ln_n_eff=12.0)
    assert common.by == "wafer"
    assert np.all(np.abs(common.share - b) < 4 * common.sigma)
    assert common.partitions["all"] - common.partitions["wafer"] > 100
    coupled = np.zeros(len(pairs))
    coupled[[3, 17]] = 0.05
    sparse = fit_common_mode(ctx, pairs, coupled + rng.normal(0, 0.004, len(pairs)), sigma, 12.0)
    # two pairs' chi^2 of ~300 cannot pay 8 parameters' ln N_eff and the pattern's misfit
    assert sparse.delta_bic > -2 * 0.05**2 / 0.004**2 + 2 * 12.0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("key", "n_pixels", "coupled"), [("wafer", 7, False), ("wafer", 7, True), ("pixel", 1, False)]
)
def test_toasts_common_mode_noise_is_not_crosstalk(tmp_path, sky_fits, key, n_pixels, coupled):
    """TOAST's CommonModeNoise (15 uK sqrt(s) common to each wafer, beside each detector's
    50): named common_mode_noise with the wafers as its scope and its share of the noise
    within 20 %, no crosstalk; with TOAST's CrossTalk coupling one pair across the wafers
    (5 %) beside it, that pair as crosstalk too, x within 3 sigma. In a pair the two are
    one signal: crosstalk, with common_mode_noise as its look-alike."""
    pytest.importorskip("toast", reason="the toast extra is not installed")
    from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

    path = write_toast_recording(
        tmp_path,
        sky_fits,
        hours=1.0,
        seed=3,
        n_pixels=n_pixels,
        wafers=2 if n_pixels > 1 else 1,
        a2_k=A2_K,
        common_mode=(15.0, 20.0, key),
        crosstalk={(0, 9): 0.05} if coupled else None,
    )
    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    names = [e["name"] for e in result["effects"]]
    if n_pixels == 1:
        assert names == ["detector_crosstalk"], names
        assert result["effects"][0]["look_alikes"] == ["common_mode_noise"]
        return
    if coupled:
        assert names == ["common_mode_noise", "detector_crosstalk"], names
        taken = {k: p for k, p in result["effects"][1]["parameters"].items() if p.get("taken")}
        assert list(taken) == ["x[D0A-140-D4B-140]"], taken
        (x,) = taken.values()
        assert abs(x["value"] - 0.05) < 3 * x["sigma"], x
        return
    assert names == ["common_mode_noise"], names
    (entry,) = result["effects"]
    assert entry["scope"]["by"] == "wafer"
    shares = [p["value"] ** 2 for p in entry["parameters"].values()]
    expected = 15.0**2 / (15.0**2 + 50.0**2)  # the common part of each white noise
    assert abs(np.median(shares) / expected - 1) < 0.2, (shares, expected)
