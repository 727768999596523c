"""The data model shared by the simulation and the diagnosis's nominal model."""

import numpy as np

from hwp_tes_systematics.simulation import data_model


def test_hwpss_with_a_phase_is_add_2f_at_a_shifted_offset():
    """A cos(2 (chi - theta) - phi) through add_2f with offset theta + phi / 2."""
    chi = np.linspace(0.0, 20.0, 1001)
    theta = np.array([0.0, np.pi / 2])
    amplitude = np.array([0.3, 0.5])
    phase = np.array([0.2, -1.1])
    got = data_model.hwpss(chi, theta, amplitude, phase)
    want = amplitude[:, None] * np.cos(2 * (chi[None] - theta[:, None]) - phase[:, None])
    np.testing.assert_allclose(got, want, atol=1e-14)
    assert not data_model.hwpss(chi, theta, 0.0).any()


def test_scan_and_its_quadrature():
    """scan = I + rho (Q cos 2a + U sin 2a) with 2a = 2 (2 chi + psi) - 2 theta; the
    quadrature is half the derivative of the polarisation term with respect to theta."""
    rng = np.random.default_rng(1)
    sky = rng.normal(size=(3, 12))
    n = 50
    chi, psi = rng.uniform(0, 2 * np.pi, (2, n))
    theta, rho = np.array([0.1, 0.9]), np.array([0.98, 0.95])
    pixels = rng.integers(0, 12, (2, n))
    angles = data_model.polarisation_angles(chi, psi, theta)
    twice_alpha = 2 * (2 * chi[None] + psi[None]) - 2 * theta[:, None]
    np.testing.assert_allclose(angles[0], np.cos(twice_alpha), atol=1e-12)
    total = data_model.scan(pixels, *angles, rho, sky)
    want = sky[0][pixels] + rho[:, None] * (
        sky[1][pixels] * np.cos(twice_alpha) + sky[2][pixels] * np.sin(twice_alpha)
    )
    np.testing.assert_allclose(total, want, atol=1e-12)
    polarisation = data_model.scan(pixels, *angles, rho, sky, intensity=False)
    np.testing.assert_allclose(polarisation, want - sky[0][pixels], atol=1e-12)
    step = 1e-6
    shifted = data_model.polarisation_angles(chi, psi, theta + step)
    derivative = (
        data_model.scan(pixels, *shifted, rho, sky, intensity=False) - polarisation
    ) / step
    quadrature = data_model.scan_quadrature(pixels, *angles, rho, sky)
    np.testing.assert_allclose(quadrature, derivative / 2, atol=1e-5)


def test_scanning_rates_are_the_ptep_ones():
    spin_hz, precession_hz = data_model.scanning_rates_hz()
    assert np.isclose(spin_hz, 0.05 / 60.0) and np.isclose(precession_hz, 1 / (192.348 * 60.0))
