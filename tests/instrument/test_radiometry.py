"""Band power and K/W conversion against analytic results."""

import numpy as np
import pytest
from scipy.constants import h, k

from hwp_tes_systematics.instrument.radiometry import (
    T_CMB_K,
    band_power_w,
    dpower_dtemperature_w_per_k,
    kelvin_per_watt,
    photon_occupation,
    top_hat_bandpass,
)


def test_rayleigh_jeans_limit_is_k_t_delta_nu_eta():
    """h nu << k T: P = k T Delta nu eta for a top-hat band."""
    band = top_hat_bandpass(center_ghz=1.0, width_ghz=0.2)
    temperature_k, efficiency = 300.0, 0.37
    expected_w = k * temperature_k * 0.2e9 * efficiency
    # first correction of h nu n = k T (1 - x/2 + ...) is x/2 ~ 1e-4 at 1 GHz, 300 K
    assert band_power_w(band, temperature_k, efficiency) == pytest.approx(expected_w, rel=2e-4)


def test_wien_side_is_far_below_rayleigh_jeans():
    band = top_hat_bandpass(center_ghz=400.0, width_ghz=90.0)
    assert band_power_w(band, 2.725) < 0.05 * k * 2.725 * 90e9


def test_top_hat_dp_dt_matches_analytic_derivative():
    """dP/dT of a top-hat band: finite difference of P vs integral of k x^2 e^x/(e^x-1)^2."""
    band = top_hat_bandpass(center_ghz=140.0, width_ghz=42.0)
    step_k = 1e-5
    finite_difference = (
        band_power_w(band, T_CMB_K + step_k) - band_power_w(band, T_CMB_K - step_k)
    ) / (2 * step_k)
    analytic = dpower_dtemperature_w_per_k(band, T_CMB_K)
    assert finite_difference == pytest.approx(analytic, rel=1e-7)
    # independent check by direct quadrature on a fine grid
    freqs_hz = np.linspace(119e9, 161e9, 200001)
    x = h * freqs_hz / (k * T_CMB_K)
    direct = np.trapezoid(k * x**2 * np.exp(x) / np.expm1(x) ** 2, freqs_hz)
    assert analytic == pytest.approx(direct, rel=1e-6)


def test_kelvin_per_watt_four_steps():
    band = top_hat_bandpass(center_ghz=100.0, width_ghz=23.0)
    result = kelvin_per_watt(band, efficiency=0.5, delta_t_k=1e-3)
    assert result["delta_p_w"] == pytest.approx(result["p_cmb_shifted_w"] - result["p_cmb_w"])
    assert result["kelvin_per_watt"] == pytest.approx(1e-3 / result["delta_p_w"])
    # 1 mK step: C agrees with 1/(dP/dT) to second order, delta T / (2 T) ~ 2e-4 at most
    analytic = 1.0 / dpower_dtemperature_w_per_k(band, T_CMB_K, 0.5)
    assert result["kelvin_per_watt"] == pytest.approx(analytic, rel=5e-4)


def test_occupation_number_limits():
    assert photon_occupation(1e-3, 10.0) == pytest.approx(k * 10 / (h * 1e6), rel=1e-3)
    assert photon_occupation(1000.0, 2.725) < 1e-7


def test_negative_temperature_is_rejected():
    with pytest.raises(ValueError, match="temperature_k = -1"):
        band_power_w(top_hat_bandpass(100.0, 20.0), -1.0)
