"""The diagnosis's FFTs (diagnose.fourier) against scipy.fft's conventions."""

import numpy as np
import pytest
import scipy.fft

from hwp_tes_systematics.diagnose.fourier import irfft, rfft


@pytest.mark.parametrize("n", [16, 17, 1000, 1001])
def test_rfft_and_irfft_follow_scipy(n):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(3, n))
    assert np.allclose(rfft(x), scipy.fft.rfft(x, axis=-1), rtol=0, atol=1e-12 * n)
    assert np.allclose(rfft(x.T, axis=0), scipy.fft.rfft(x.T, axis=0), rtol=0, atol=1e-12 * n)
    # any imaginary part at f = 0 (and n/2) is ignored, as by scipy
    spectrum = rng.normal(size=(3, n // 2 + 1)) + 1j * rng.normal(size=(3, n // 2 + 1))
    assert np.allclose(irfft(spectrum, n), scipy.fft.irfft(spectrum, n=n), rtol=0, atol=1e-14)
    assert np.allclose(irfft(rfft(x), n), x, rtol=0, atol=1e-12)


def test_irfft_pads_or_truncates_the_spectrum_as_scipy():
    rng = np.random.default_rng(1)
    spectrum = rng.normal(size=40) + 1j * rng.normal(size=40)
    for n in (30, 78, 79, 120):  # fewer and more coefficients than n // 2 + 1
        assert np.allclose(irfft(spectrum, n), scipy.fft.irfft(spectrum, n=n), atol=1e-14)


def test_rfft_into_a_given_array_and_of_integers():
    x = np.arange(12)
    out = np.empty(7, dtype=complex)
    result = rfft(x.astype(np.float32), out=out)
    assert result is out or np.shares_memory(result, out)
    assert np.allclose(out, scipy.fft.rfft(x))
    assert np.allclose(rfft(x), scipy.fft.rfft(x))
