"""Tests of the steady-state electrothermal TES model and its response-curve figure."""

import math
from dataclasses import replace

import numpy as np
import pytest

from hwp_tes_systematics.figures.tes import plot_response_curve
from hwp_tes_systematics.instrument.tes import (
    TesParameters,
    bias_voltage_for_resistance,
    nonlinearity_coefficients,
    optical_power_for_resistance,
    responsivity_a_per_w,
    solve_operating_point,
    tes_parameters_for_channel,
)

P_NOMINAL_W = 0.4e-12  # Psat = 2.5 x 0.4 pW = 1 pW
KELVIN_PER_WATT = 7e12


@pytest.fixture(scope="module")
def params():
    return tes_parameters_for_channel(P_NOMINAL_W, psat_factor=2.5, resistance_fraction=0.7)


def test_high_loop_gain_responsivity_is_minus_inverse_tes_voltage(params):
    sharp = replace(
        params,
        transition_width_k=1e-6,
        critical_current_a=math.inf,
        thevenin_resistance_ohm=1e-4,
    )
    sharp = replace(sharp, bias_voltage_v=bias_voltage_for_resistance(sharp, P_NOMINAL_W, 0.7))
    tes_voltage_v = float(solve_operating_point(sharp, P_NOMINAL_W).tes_voltage_v)
    responsivity = float(responsivity_a_per_w(sharp, P_NOMINAL_W))
    assert abs(responsivity * tes_voltage_v + 1.0) < 1e-2


def test_operating_point_satisfies_model_equations(params):
    powers_w = np.array([0.1, 0.4, 0.55, 1.2]) * params.psat_w
    point = solve_operating_point(params, powers_w)
    resistance_ohm = params.resistance_ohm(point.temperature_k, point.current_a)
    np.testing.assert_allclose(point.resistance_ohm, resistance_ohm, rtol=1e-12)
    np.testing.assert_allclose(
        point.current_a * (params.thevenin_resistance_ohm + resistance_ohm),
        params.bias_voltage_v,
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        powers_w + point.joule_power_w, params.bath_power_w(point.temperature_k), rtol=1e-12
    )
    np.testing.assert_array_equal(point.is_normal, [False, False, False, True])


def test_current_decreases_with_optical_power(params):
    p_normal_w = optical_power_for_resistance(params, 0.99)
    reached = solve_operating_point(params, p_normal_w)
    assert float(reached.resistance_ohm) == pytest.approx(0.99 * params.rn_ohm, rel=1e-9, abs=0.0)
    # Voltage bias keeps dissipating ~V^2/Rn when normal: the optical saturation is below Psat.
    assert 0.4 * params.psat_w < p_normal_w < params.psat_w

    powers_w = np.linspace(0.05, 0.95, 91) * params.psat_w
    currents_a = solve_operating_point(params, powers_w).current_a
    in_transition = powers_w <= p_normal_w
    assert np.all(np.diff(currents_a[in_transition]) < 0.0)
    assert np.all(np.diff(currents_a) <= 0.0)


def test_tes_is_normal_above_saturation(params):
    p_high_w = 1.2 * params.psat_w
    point = solve_operating_point(params, p_high_w)
    assert bool(point.is_normal)
    assert float(point.resistance_ohm) == pytest.approx(params.rn_ohm, rel=1e-6, abs=0.0)
    normal_current_a = params.bias_voltage_v / (params.thevenin_resistance_ohm + params.rn_ohm)
    assert float(point.current_a) == pytest.approx(normal_current_a, rel=1e-6, abs=0.0)
    nominal_responsivity = float(responsivity_a_per_w(params, P_NOMINAL_W))
    assert abs(float(responsivity_a_per_w(params, p_high_w))) < 1e-3 * abs(nominal_responsivity)


@pytest.mark.parametrize("resistance_fraction", [0.3, 0.7, 0.9])
def test_bias_voltage_round_trip(params, resistance_fraction):
    bias_voltage_v = bias_voltage_for_resistance(params, P_NOMINAL_W, resistance_fraction)
    point = solve_operating_point(replace(params, bias_voltage_v=bias_voltage_v), P_NOMINAL_W)
    assert float(point.resistance_ohm) == pytest.approx(
        resistance_fraction * params.rn_ohm, rel=1e-6, abs=0.0
    )
    assert not bool(point.is_normal)


def test_bias_voltage_requires_power_below_saturation(params):
    with pytest.raises(ValueError, match="psat_w"):
        bias_voltage_for_resistance(params, params.psat_w, 0.7)


def test_nonlinearity_coefficients_match_responsivity_slope(params):
    coefficients = nonlinearity_coefficients(params, P_NOMINAL_W, KELVIN_PER_WATT, 1e-13)
    responsivity0 = coefficients["responsivity_a_per_w"]
    assert responsivity0 == pytest.approx(float(responsivity_a_per_w(params, P_NOMINAL_W)))

    step_w = 1e-15
    responsivity_slope = float(
        np.diff(responsivity_a_per_w(params, P_NOMINAL_W + np.array([-step_w, step_w])))[0]
        / (2.0 * step_w)
    )
    g1_finite_difference = responsivity_slope / (2.0 * responsivity0 * KELVIN_PER_WATT)
    assert coefficients["g1_per_k"] == pytest.approx(g1_finite_difference, rel=1e-2, abs=0.0)
    assert coefficients["dsdp_a_per_w2"] == pytest.approx(responsivity_slope, rel=1e-2, abs=0.0)
    # |S| falls with power (S < 0 and increasing towards 0): g1 < 0.
    assert responsivity0 < 0.0
    assert coefficients["g1_per_k"] < 0.0


def test_nonlinearity_polynomial_reproduces_calibrated_response(params):
    half_range_w = 5e-14
    coefficients = nonlinearity_coefficients(params, P_NOMINAL_W, KELVIN_PER_WATT, half_range_w)
    offset_w = 0.5 * half_range_w
    currents_a = solve_operating_point(params, [P_NOMINAL_W, P_NOMINAL_W + offset_w]).current_a
    d_est_w = (currents_a[1] - currents_a[0]) / coefficients["responsivity_a_per_w"]
    polynomial_w = np.polynomial.polynomial.polyval(
        offset_w, coefficients["polynomial_coefficients"]
    )
    assert polynomial_w == pytest.approx(d_est_w, rel=1e-6, abs=0.0)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("tc_k", 0.0),
        ("tbath_k", -0.1),
        ("tbath_k", 0.2),
        ("thermal_exponent_n", 0.0),
        ("psat_w", -1e-12),
        ("rn_ohm", 0.0),
        ("transition_width_k", 0.0),
        ("critical_current_a", 0.0),
        ("thevenin_resistance_ohm", -0.01),
        ("bias_voltage_v", -1e-7),
        ("bias_voltage_v", math.nan),
    ],
)
def test_bad_parameters_raise_naming_the_parameter(name, value):
    arguments = {"psat_w": 1e-12, "bias_voltage_v": 1e-7, name: value}
    with pytest.raises(ValueError, match=rf"tes\.{name} = {value!r}: expected"):
        TesParameters(**arguments)


def test_response_curve_figure_is_written_atomically(params, tmp_path):
    path = tmp_path / "tes_response.png"
    written = plot_response_curve(params, P_NOMINAL_W, 0.05e-12, "M1-140", path)
    assert written == path
    assert path.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert path.stat().st_size > 1000
    assert list(tmp_path.iterdir()) == [path]
