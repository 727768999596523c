"""The diagnosis finds injected effects it was not told about, with the right parameters.

Each recording (1-2 h of the M1-140 pair, written to HDF5 and read back) carries one effect
(or two) at a clearly detectable but realistic level and its own noise seed; ``diagnose``
gets the recording, the sky, A_2 and the configured noise only. Checks: the top-ranked
effect is the injected one, its main parameter(s) lie within 3 sigma of the truth for
each detector, and chi^2 improves. Effects that ARE nominal-model errors (a time
constant on a pure 2f HWPSS, crosstalk within the pair, a noise level) must come out as
nominal adjustments with the right values, not as effects.
"""

from __future__ import annotations

import math
import shutil

import h5py
import numpy as np
import pytest

from hwp_tes_systematics.diagnose.testbed import (
    A2_K,
    KELVIN_PER_WATT,
    P0_W,
    recorded,
    run,
)

pytestmark = pytest.mark.slow

# name, injected parameters, {parameter: per-detector truth} checked at 3 sigma, noise seed
SINGLE = [
    ("tes_nonlinearity", {"g1": [-0.04, -0.045]}, {"g1": [-0.04, -0.045]}, 101),
    (
        "hwpss_harmonics",
        {"c1": 20e-6, "s3": 15e-6, "c4": [30e-6, 25e-6], "s4": -10e-6, "c2": 50e-6},
        {
            "c1": [20e-6] * 2,
            "s3": [15e-6] * 2,
            "c4": [30e-6, 25e-6],
            "s4": [-10e-6] * 2,
        },
        103,
    ),
    (
        "hwpss_intensity_coupling",
        {"a2c": 0.01, "a2s": -0.004},
        {"a2c": [0.01] * 2, "a2s": [-0.004] * 2},
        104,
    ),
    (  # each TES its own drift (one HWP would drift both by the same relative amount)
        "gain_drift",
        {"g1": [0.03, 0.018], "g2": [0.005, 0.002]},
        {"g1": [0.03, 0.018], "g2": [0.005, 0.002]},
        105,
    ),
    ("hwp_temperature_drift", {"c1": 1e-3, "c2": 3e-4}, {"c1": [1e-3] * 2, "c2": [3e-4] * 2}, 106),
    (  # the HWP's I -> P leakage at 4 f_HWP: the dipole's 4f +- f_spin sidebands ~10 uK
        "hwp_intensity_leakage_4f",
        {"b4c": 0.01, "b4s": -0.006},
        {"b4c": [0.01] * 2, "b4s": [-0.006] * 2},
        107,
    ),
]

GLITCHES = [
    (0, 900.0, 3e-3, 0.1),
    (0, 3100.0, 5e-3, 0.05),
    (1, 2000.0, 6e-3, 0.2),
    (1, 3500.0, 2.5e-3, 0.1),
]


def check_parameters(result, effect, truths):
    for param, truth in truths.items():
        for k, value in enumerate(truth):
            entry = result.parameter(effect, param, k)
            pull = (entry["value"] - value) / entry["sigma"]
            assert abs(pull) < 3, (
                f"{effect}.{param}[{k}] = {entry['value']:.4g} +- {entry['sigma']:.2g}, truth {value:.4g}"
            )


@pytest.mark.parametrize("effect, injected, truths, seed", SINGLE, ids=[s[0] for s in SINGLE])
def test_single_effect_found(tmp_path, effect, injected, truths, seed):
    recording, _ = recorded(tmp_path, [(effect, injected)], noise_seed=seed, hours=1.0)
    result = run(recording)
    assert result["mismatch_found"]
    assert result.effect_names[0] == effect, result.effect_names
    assert result.effect_names == [effect], f"spurious effects: {result.effect_names}"
    check_parameters(result, effect, truths)
    assert result["unexplained"] == [], result["unexplained"]
    # the evidence is measured on the recording (the effect's own text), not its signature
    top = result["effects"][0]
    assert top["evidence"] != top["signature"] and "sigma" in top["evidence"], top["evidence"]
    assert not top["partial"], top["evidence"]  # its own lines fully described
    if effect == "tes_nonlinearity":  # its 2f +- f_spin sidebands seen: no look-alike
        assert top["look_alikes"] == [], top["look_alikes"]
    if effect == "hwpss_harmonics":  # its c2 is a 2f amplitude error: an adjustment
        # found line by line: the injected lines, and no other
        assert sorted(top["members"]) == [f"hwpss_harmonic_{n}" for n in (1, 3, 4)], top
        for k in range(2):
            a2 = result.adjustment(k, "hwpss_2f_amplitude")
            assert abs(a2["value"] - (A2_K + 50e-6)) < 3 * a2["sigma"] + 1e-9, a2
    # under the final noise no look-alike in a linear effect's place fits better
    margins = result["swap_margins"]["effects"]
    assert effect in margins or effect in {"tes_nonlinearity", "hwpss_harmonics"}, margins
    for alternatives in margins.values():
        assert alternatives and min(alternatives.values()) >= 0, margins
    assert result["chi2_after"] < result["chi2_before"]
    # the fit leaves chi^2 consistent with noise: chi^2 / dof ~ 1
    assert abs(result["chi2_after"] / result["dof"] - 1) < 5 * math.sqrt(2 / result["dof"])


def test_glitches_found(tmp_path):
    recording, _ = recorded(
        tmp_path, [("glitches", {"events": GLITCHES})], noise_seed=108, hours=1.0
    )
    result = run(recording)
    assert result.effect_names == ["glitches"]
    fitted = [p for p in result["effects"][0]["parameters"].values()]
    for detector, time_s, amplitude, _tau in GLITCHES:
        name = result["recording"]["detectors"][detector]
        times = [p for p in fitted if p["parameter"] == "time" and p["detector"] == name]
        match = [p for p in times if abs(p["value"] - time_s) < 0.1]
        assert match, f"glitch at {time_s} s in detector {detector} not found"
    amplitudes = sorted((p["value"], p["sigma"]) for p in fitted if p["parameter"] == "amplitude")
    truth = sorted(a for _, _, a, _ in GLITCHES)
    assert len(amplitudes) == len(truth)
    for (value, sigma), expected in zip(amplitudes, truth, strict=True):
        assert abs(value - expected) < 3 * sigma
    assert result["chi2_after"] < result["chi2_before"]


def test_noise_level_is_an_adjustment(tmp_path):
    """NET 20 % high and a 3x knee: fitted as the noise adjustment, not reported as physics."""
    recording, _ = recorded(
        tmp_path,
        [("noise_mismatch", {"net_ukrts": 64.8, "fknee_mhz": 60.0})],
        noise_seed=109,
        hours=1.0,
    )
    result = run(recording)
    assert not result["mismatch_found"], (result.effect_names, result["unexplained"])
    for k in range(2):
        net = result.adjustment(k, "noise_net")
        assert abs(net["value"] - 64.8) < 3 * net["sigma"], net
        assert net["nominal"] != pytest.approx(64.8)
        fknee = result.adjustment(k, "noise_fknee")
        assert abs(fknee["value"] - 60.0) < 3 * fknee["sigma"], fknee


def test_time_constant_is_a_2f_phase_adjustment(tmp_path):
    """On a pure 2f HWPSS, tau lags the 2f line by atan(2 pi 2 f_HWP tau): a 2f phase error.

    Its other signatures (lag of the dipole and sky band) are ~1e-7 K here, so the two are
    one signal; the adjustment reports the equivalent time constant tan(phi)/(2 pi 2 f_HWP).
    """
    taus = [3e-3, 4e-3]
    recording, _ = recorded(
        tmp_path, [("detector_time_constant", {"tau": taus})], noise_seed=102, hours=1.0
    )
    result = run(recording)
    assert not result["mismatch_found"], (result.effect_names, result["unexplained"])
    f_hwp = result["recording"]["f_hwp_hz"]
    for k, tau in enumerate(taus):
        phase = result.adjustment(k, "hwpss_2f_phase")
        equivalent = phase["equivalent_time_constant_s"]
        sigma_tau = math.radians(phase["sigma"]) / (2 * math.pi * 2 * f_hwp)
        assert abs(equivalent - tau) < 3 * sigma_tau + 1e-6, (equivalent, tau, sigma_tau)
        # the amplitude loss 1/sqrt(1 + (2 pi 2 f_HWP tau)^2) is in the 2f amplitude
        a2 = result.adjustment(k, "hwpss_2f_amplitude")
        expected = A2_K / math.sqrt(1 + (2 * math.pi * 2 * f_hwp * tau) ** 2)
        assert abs(a2["value"] - expected) < 3 * a2["sigma"] + 1e-9


def test_crosstalk_is_absorbed_by_adjustments(tmp_path):
    """x d_other in a co-pointed pair = gain (1 + x) and A_2 |1 + x exp(2i (theta - theta'))|.

    For exactly orthogonal angles the 2f amplitude is A_2 (1 - x); the M1-140 pair is
    91.6 deg apart, which the 2f amplitude shows at the 1e-6 K level.
    """
    xs = [0.01, 0.005]
    recording, _ = recorded(tmp_path, [("crosstalk", {"x": xs})], noise_seed=107, hours=1.0)
    result = run(recording)
    assert not result["mismatch_found"], (result.effect_names, result["unexplained"])
    theta = recording.pol_angles_rad
    for k, x in enumerate(xs):
        a2 = result.adjustment(k, "hwpss_2f_amplitude")
        expected = A2_K * abs(1 + x * np.exp(2j * (theta[k] - theta[1 - k])))
        assert abs(a2["value"] - expected) < 3 * a2["sigma"] + 1e-9, (a2, expected)
        gain = result.adjustment(k, "gain")
        assert abs(gain["value"] - (1 + x)) < 3 * gain["sigma"], gain


def test_nonlinearity_and_gain_drift_both_found(tmp_path):
    """Each TES its own gain drift, then its nonlinearity on the drifting signal."""
    drifts = [0.03, 0.02]
    effects = [("gain_drift", {"g1": drifts}), ("tes_nonlinearity", {"g1": -0.04})]
    recording, _ = recorded(tmp_path, effects, noise_seed=110)
    result = run(recording)
    assert sorted(result.effect_names) == ["gain_drift", "tes_nonlinearity"]
    for k in range(2):
        g1 = result.parameter("tes_nonlinearity", "g1", k)
        assert abs(g1["value"] + 0.04) < 3 * g1["sigma"]
        gain = result.parameter("gain_drift", "g1", k)
        assert abs(gain["value"] - drifts[k]) < 3 * gain["sigma"]


def test_harmonics_and_glitches_both_found(tmp_path):
    effects = [
        ("hwpss_harmonics", {"c4": 30e-6, "s1": 40e-6}),
        ("glitches", {"events": GLITCHES[:2]}),
    ]
    recording, _ = recorded(tmp_path, effects, noise_seed=111, hours=1.0)
    result = run(recording)
    assert sorted(result.effect_names) == ["glitches", "hwpss_harmonics"]
    for k in range(2):
        c4 = result.parameter("hwpss_harmonics", "c4", k)
        assert abs(c4["value"] - 30e-6) < 3 * c4["sigma"]


def test_electrothermal_tes_is_diagnosed_as_nonlinearity(tmp_path):
    """A recording whose nonlinearity comes from the TES model, not from a polynomial."""
    from hwp_tes_systematics.instrument import tes

    recording, _ = recorded(
        tmp_path,
        [("tes_electrothermal", {"p0_w": P0_W, "kelvin_per_watt": KELVIN_PER_WATT})],
        noise_seed=112,
        hours=1.0,
    )
    result = run(recording)
    # its cubic term is strong enough to pay for g2: the nested extension is kept
    assert result.effect_names[0] == "tes_nonlinearity_cubic"
    params = tes.tes_parameters_for_channel(P0_W)
    half_range_w = 1.05 * A2_K / KELVIN_PER_WATT
    expected = tes.nonlinearity_coefficients(params, P0_W, KELVIN_PER_WATT, half_range_w)
    for k in range(2):
        g1 = result.parameter("tes_nonlinearity_cubic", "g1", k)
        g2 = result.parameter("tes_nonlinearity_cubic", "g2", k)
        assert g1["value"] == pytest.approx(expected["g1_per_k"], rel=0.10, abs=3 * g1["sigma"])
        assert g2["value"] == pytest.approx(expected["g2_per_k2"], rel=0.10, abs=3 * g2["sigma"])
        assert np.sign(g1["value"]) == np.sign(expected["g1_per_k"])


def test_strong_nonlinearity_fitted_on_the_pre_nonlinearity_signal(tmp_path):
    """H3-402 (A_2 = 3.8 K) with nominal errors and g1 A_2 ~ 0.04, injected last as
    litebird_sim does (d + g1 d^2 on the recorded TOD). The adjusted nominal model holds the
    nonlinearity's DC and 2f terms; a template d_nom^2 built on it is off by ~1e-3 of the
    4f line (thousands of chi^2 at this S/N: a free 4f line + intensity coupling won, and g1
    was 0.3 % = 30 sigma off). Rebuilt on the pre-nonlinearity model it is exact."""
    from hwp_tes_systematics.diagnose import diagnose
    from hwp_tes_systematics.diagnose.recording import read_recording
    from hwp_tes_systematics.diagnose.testbed import (
        nominal,
        nominal_errors,
        recorded_with_errors,
        supplied_sky,
    )

    channel = "H3-402"
    errors = nominal_errors(np.random.default_rng(2913))
    recording, _ = recorded_with_errors(
        tmp_path, [], 2913, errors, hours=1.0, name="clean.h5", channel=channel
    )
    g1 = np.array([-0.0105, -0.0095])  # 1/K
    shutil.copy(tmp_path / "clean.h5", tmp_path / "nl.h5")
    with h5py.File(tmp_path / "nl.h5", "r+") as f:
        f["tod"][...] = recording.tod + g1[:, None] * recording.tod**2
    result = diagnose(
        read_recording(tmp_path / "nl.h5"),
        supplied_sky(errors),
        nominal(channel)["a2_k"],
        figures=False,
    )
    # nothing else: no free 4f line, and no gain fluctuation reported with Delta BIC > 0
    # (one was, when the early roll-off it sat beside was dropped)
    assert result.effect_names == ["tes_nonlinearity"], [
        (e["name"], e["delta_bic"]) for e in result["effects"]
    ]
    for k in range(2):
        fitted = result.parameter("tes_nonlinearity", "g1", k)
        assert abs(fitted["value"] - g1[k]) < 3 * fitted["sigma"], (fitted, g1[k])


def test_a_nonlinearity_beside_a_4f_harmonic_is_bounded_by_every_solution(tmp_path):
    """H3-402 for a quarter of an hour, g1 beside a 1 mK HWPSS harmonic at 4 f_HWP: the
    harmonic takes the 4f line g1 A_2^2 / 2 (39 mK here) at first order, and only the
    cross terms of the composition (g1 x 2 A_2 x the harmonic) and the weak 2 f_HWP +- sky
    sidebands tell the two apart. The composed fit walked away from the minimum (chi^2
    up by 7) to g1 ~ 0 +- 1e-4 and bounded |g1| by 5e-4 against an injected 5.5e-3. Now
    the lowest pass is kept, the fit is started three ways, and the bound covers the
    injected g1 on both detectors, naming the second solution."""
    from hwp_tes_systematics.diagnose import diagnose
    from hwp_tes_systematics.diagnose.testbed import (
        nominal,
        nominal_errors,
        recorded_with_errors,
        supplied_sky,
    )

    channel = "H3-402"
    rng = np.random.default_rng(4402)
    errors = nominal_errors(rng)
    g1 = np.array([-0.0055, -0.0006])  # 1/K
    phase = rng.uniform(0.0, 2 * np.pi, 2)
    a4 = {"c4": 1e-3 * np.cos(phase), "s4": 1e-3 * np.sin(phase)}
    effects = [("tes_nonlinearity", {"g1": g1}), ("hwpss_harmonics", a4)]
    recording, _ = recorded_with_errors(
        tmp_path, effects, 4402, errors, hours=0.25, name="nl_a4.h5", channel=channel
    )
    result = diagnose(recording, supplied_sky(errors), nominal(channel)["a2_k"], figures=False)
    check = result["requirement_check"]
    for k, detector in enumerate(check["detectors"]):
        bound = detector.get("bound_per_k")
        if bound is None:  # selected: the fit's g1 and its uncertainty
            assert abs(detector["g1_per_k"] - g1[k]) < 3 * detector["uncertainty_per_k"]
        else:
            assert abs(g1[k]) < bound, (detector, g1[k])
