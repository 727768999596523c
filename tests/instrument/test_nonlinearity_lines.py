"""Analytic signatures of the quadratic nonlinearity on a HWP synchronous signal."""

import numpy as np
import pytest

from hwp_tes_systematics.instrument.nonlinearity import apply_nonlinearity
from hwp_tes_systematics.simulation.spectral import amplitude_spectrum, line_amplitude

SAMPLING_RATE_HZ = 31.0
F_HWP_HZ = 39.0 / 60.0
TIMES_S = np.arange(int(3 * 3600 * SAMPLING_RATE_HZ)) / SAMPLING_RATE_HZ
CHI = 2 * np.pi * F_HWP_HZ * TIMES_S


def test_2f_hwpss_gives_4f_line_and_dc_of_g1_a2_over_2():
    amplitude_k, g1_per_k = 0.3, -2e-3
    tod = amplitude_k * np.cos(2 * CHI)
    leakage = apply_nonlinearity(tod, g1_per_k) - tod
    line, _ = line_amplitude(leakage, TIMES_S, 4 * F_HWP_HZ)
    assert line == pytest.approx(abs(g1_per_k) * amplitude_k**2 / 2, rel=1e-9)
    assert leakage.mean() == pytest.approx(g1_per_k * amplitude_k**2 / 2, rel=1e-6)


def test_dipole_intermodulation_at_2f_plus_minus_fd():
    amplitude_k, dipole_k, g1_per_k = 0.3, 3e-3, 1e-2
    f_dipole_hz = 1.0 / 600.0  # a fast 'spin' for a short test; only the mixing matters
    dipole = dipole_k * np.cos(2 * np.pi * f_dipole_hz * TIMES_S)
    tod = amplitude_k * np.cos(2 * CHI) + dipole
    leakage = apply_nonlinearity(tod, g1_per_k) - tod
    for freq_hz in (2 * F_HWP_HZ - f_dipole_hz, 2 * F_HWP_HZ + f_dipole_hz):
        line, _ = line_amplitude(leakage, TIMES_S, freq_hz)
        assert line == pytest.approx(g1_per_k * amplitude_k * dipole_k, rel=1e-6)
    freqs, spectrum = amplitude_spectrum(leakage, SAMPLING_RATE_HZ)
    peak = np.argmax(np.where(np.abs(freqs - 2 * F_HWP_HZ) < 0.05, spectrum, 0))
    assert abs(abs(freqs[peak] - 2 * F_HWP_HZ) - f_dipole_hz) < 2 / TIMES_S[-1]


def test_per_detector_g1_and_cubic_term():
    tod = np.vstack([np.full(4, 2.0), np.full(4, 2.0)])
    out = apply_nonlinearity(tod, np.array([0.1, -0.1]), np.array([0.0, 0.01]))
    np.testing.assert_allclose(out[0], 2.0 + 0.4)
    np.testing.assert_allclose(out[1], 2.0 - 0.4 + 0.08)


def test_matches_litebird_sim_quadratic_nonlinearity():
    import litebird_sim as lbs

    tod = np.random.default_rng(3).normal(scale=0.2, size=1000)
    expected = tod.copy()
    lbs.non_linearity.apply_quadratic_nonlin_for_one_detector(
        expected,
        nl_params=lbs.NonLinParams(sampling_gaussian_loc=-3e-3, sampling_gaussian_scale=0.0),
        random=np.random.default_rng(0),
    )
    np.testing.assert_allclose(apply_nonlinearity(tod, -3e-3), expected, rtol=1e-15)


def test_linearize_with_the_true_g1_removes_the_nonlinearity_to_rounding():
    """The TOD correction of a calibration: with g1_hat = g1 the quadratic response is
    undone to rounding (per detector row); with an error delta = g1 - g1_hat what is left
    is the nonlinearity of g1 = delta, to O(g1 delta d^3)."""
    from hwp_tes_systematics.instrument.nonlinearity import linearize

    rng = np.random.default_rng(7)
    time_s = np.arange(20000) / 19.0
    tod = 3e-3 * np.cos(2 * np.pi * 0.01 * time_s) + 0.5 * np.cos(2 * np.pi * 2 * 0.77 * time_s)
    tod = np.array([tod, tod + 1e-4 * rng.standard_normal(tod.size)])  # K: dipole + HWPSS
    g1 = np.array([0.05, -0.03])
    corrected = linearize(apply_nonlinearity(tod, g1), g1)
    np.testing.assert_allclose(corrected, tod, rtol=0, atol=1e-15)
    delta = np.array([1e-3, -2e-3])
    left = linearize(apply_nonlinearity(tod, g1), g1 - delta) - tod
    expected = delta[:, None] * tod**2
    bound = 4 * np.abs(g1 * delta)[:, None] * np.abs(tod) ** 3
    assert np.all(np.abs(left - expected) <= bound + 1e-16)
    assert np.abs(left - expected).max() < 0.1 * np.abs(expected).max()
    np.testing.assert_array_equal(linearize(tod, 0.0), tod)  # g1_hat = 0: no correction
    with pytest.raises(ValueError, match="extremum"):
        linearize(np.array([-10.0]), 0.05)
