"""Pointing offsets (issue 29): the offset directions are litebird_sim's focal-plane axes, the
template recovers an offset injected by rotating the detector quaternions (the recording
keeping the nominal pointing), and the diagnosis names and fits it (M1-140 pair, nside-32
CMB sky, six hours; detection thresholds: benchmarks/pointing_threshold.py)."""

import math

import litebird_sim as lbs
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import simulate
from hwp_tes_systematics.diagnose.model import (
    ARCMIN_RAD,
    build_context,
    displaced_pointings,
    focal_plane_axes,
)
from hwp_tes_systematics.diagnose.recording import DEFAULT_START_TDB
from hwp_tes_systematics.diagnose.testbed import (
    A2_K,
    CHANNEL,
    MASTER_SEED,
    recorded,
    run,
    sky_map,
)


def _angle_arcmin(a, b):
    return np.degrees(np.linalg.norm(a - b, axis=-1)) * 60


@pytest.mark.parametrize("axis", [0, 1])
def test_a_focal_plane_rotation_moves_the_pointing_along_a_fixed_direction(axis):
    """A rotation by delta about the focal plane's x (y) axis (litebird_sim quaternions)
    moves the pointing by delta along u (v) of focal_plane_axes, at every sample."""
    simulator, pointing, _ = simulate._simulated_base(CHANNEL, 0.5, DEFAULT_START_TDB, 32)
    delta_arcmin = 5.0
    moved, _ = simulate._true_pointing(
        simulator, pointing, {("offset_x", "offset_y")[axis]: delta_arcmin}
    )
    nominal = np.asarray(pointing.ecliptic_rad())[0]
    true = np.asarray(moved.ecliptic_rad())[0]
    n, u, v = focal_plane_axes(nominal)
    n_true, _, _ = focal_plane_axes(true)
    tangent, other = (u, v) if axis == 0 else (v, u)
    along = np.degrees(np.sum((n_true - n) * tangent, axis=1)) * 60
    assert np.allclose(along, delta_arcmin, atol=1e-6)
    assert np.allclose(np.sum((n_true - n) * other, axis=1), 0, atol=1e-9)
    # and displaced_pointings inverts it
    back = displaced_pointings(nominal, axis, delta_arcmin * ARCMIN_RAD)
    assert np.max(_angle_arcmin(focal_plane_axes(back)[0], n_true)) < 1e-6


def test_the_template_recovers_an_injected_offset():
    """Recording at the true pointing minus the nominal one (the same noise), regressed on
    the gradient templates: the injected x = 5 and y = -4 arcmin to 10 % (the sky at the
    nearest pixel of an nside-32 map, a finite number of pixel crossings; the dipole exact)."""
    truth = {"offset_x": 5.0, "offset_y": -4.0}
    args = (CHANNEL, 2.0, MASTER_SEED, 3, sky_map(), A2_K)
    moved = simulate.simulate_recording(*args, [("pointing_offset", truth)])
    nominal = simulate.simulate_recording(*args, [])
    assert np.array_equal(moved.pointings_ecl, nominal.pointings_ecl)
    change = moved.tod - nominal.tod
    gradient = build_context(nominal, sky_map(), A2_K).pointing_gradient
    for k in range(2):
        fitted, *_ = np.linalg.lstsq(gradient[k].T, change[k], rcond=None)
        assert fitted == pytest.approx([truth["offset_x"], truth["offset_y"]], rel=0.1)


def test_the_dipole_template_is_exact_to_first_order():
    """With no sky the change is the dipole's alone: the first-order template explains it
    but for the second-order term, ~ offset [rad] of it (7.6 arcmin: 2.2e-3)."""
    truth = {"offset_x": -3.0, "offset_y": 7.0}
    empty_sky = np.zeros_like(sky_map())
    args = (CHANNEL, 1.0, MASTER_SEED, 3, empty_sky, A2_K)
    change = (
        simulate.simulate_recording(*args, [("pointing_offset", truth)]).tod
        - simulate.simulate_recording(*args, []).tod
    )
    nominal = simulate.simulate_recording(*args, [])
    gradient = build_context(nominal, empty_sky, A2_K).pointing_gradient
    for k in range(2):
        model = truth["offset_x"] * gradient[k, 0] + truth["offset_y"] * gradient[k, 1]
        assert np.std(change[k] - model) < 2e-3 * np.std(change[k])


def test_a_large_offset_is_not_a_time_constant():
    """An offset along the scan lags the sky like a time constant of offset / 13.8 arcmin/s
    (5 arcmin: 0.36 s); tau beyond its physical bound (50 ms) is refused."""
    from hwp_tes_systematics.diagnose.effects import DetectorTimeConstant

    assert DetectorTimeConstant.physical_bounds["tau"] == 0.05


@pytest.mark.slow
@pytest.mark.parametrize(
    ("label", "effect", "params"),
    [
        ("fixed", "pointing_offset", {"offset_x": 6.0, "offset_y": 0.0}),
        ("drifting", "pointing_drift", {"offset_x": 0.0, "offset_y": 8.0, "drift_x": 3.0}),
    ],
)
def test_the_diagnosis_names_and_fits_a_pointing_offset(tmp_path, label, effect, params):
    recording, _ = recorded(tmp_path, [(effect, params)], noise_seed=4242, hours=6.0)
    result = run(recording, figures=False)
    assert result.effect_names == [effect], (result.effect_names, result["unexplained"])
    for parameter, value in params.items():
        for k in range(2):
            fitted = result.parameter(effect, parameter, k)
            assert abs(fitted["value"] - value) < 3 * fitted["sigma"] + 0.3, (parameter, fitted)
    assert "gradient" in result.effect(effect)["evidence"]
    assert not any("tau" in p for p in result.effect(effect)["parameters"])
    assert math.isfinite(result["bic_after"])


def test_pointing_effects_need_the_gradient():
    from hwp_tes_systematics.diagnose.effects import PointingOffset
    from hwp_tes_systematics.diagnose.model import Context

    n = 8
    ctx = Context(
        times_s=np.arange(n) / 10.0,
        sampling_rate_hz=10.0,
        hwp_angle_rad=np.zeros(n),
        pol_angle_rad=np.zeros(1),
        pol_efficiency=np.ones(1),
        sky_intensity=np.zeros((1, n)),
        sky_polarization=np.zeros((1, n)),
        dipole=np.zeros((1, n)),
        a2_k=np.zeros(1),
        valid=np.ones((1, n), dtype=bool),
        detector_names=["d"],
    )
    with pytest.raises(ValueError, match="pointing_gradient"):
        PointingOffset().templates(ctx)
    assert lbs.RotQuaternion  # the injection's quaternions are litebird_sim's
