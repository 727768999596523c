"""The noise of the residual (diagnose.noise): the robust Welch estimate on gapped data."""

import numpy as np
import pytest


def one_over_f_noise(rng, n, rate_hz, net, fknee_hz, alpha=1.0):
    """White + 1/f noise of the module's model (noise.noise_psd), by FFT shaping."""
    from hwp_tes_systematics.diagnose.noise import noise_psd

    freqs = np.fft.rfftfreq(n, 1 / rate_hz)
    shape = np.sqrt(
        noise_psd(np.maximum(freqs, freqs[1]), net, fknee_hz, alpha, 1e-5) / (2 * net**2)
    )
    white = rng.standard_normal(n) * net * np.sqrt(rate_hz)
    return np.fft.irfft(np.fft.rfft(white) * shape, n=n)


def test_the_noise_estimate_ignores_segments_cut_by_a_gap():
    """A residual with an offset and a strong 4f line (an unfitted nonlinearity's, 21 mK):
    zeroed over a gap, it gave a Welch median with its knee at Nyquist; the estimate from
    whole valid segments equals the one without a gap, and scipy's median Welch without."""
    import scipy.signal

    from hwp_tes_systematics.diagnose.noise import estimate_noise, valid_welch

    rng = np.random.default_rng(29)
    rate, n, f_hwp = 31.0, 2**19, 61 / 60
    t = np.arange(n) / rate
    residual = (
        one_over_f_noise(rng, n, rate, 4e-4, 0.02)
        - 0.021
        + 0.021 * np.cos(2 * np.pi * 4 * f_hwp * t + 0.3)
    )
    valid = np.ones(n, dtype=bool)
    valid[n // 3 : n // 3 + n // 10] = False
    _, psd, segment = valid_welch(residual, rate, None)
    _, scipy_psd = scipy.signal.welch(
        residual, rate, "hann", segment, segment // 2, average="median"
    )
    np.testing.assert_allclose(psd, scipy_psd, rtol=1e-10)

    without = estimate_noise(residual, rate, None, f_hwp, 0.0)
    with_gap = estimate_noise(np.where(valid, residual, 0.0), rate, valid, f_hwp, 0.0)
    for estimate in (without, with_gap):
        assert estimate.model.net_k_sqrt_s == pytest.approx(4e-4, rel=0.05)
        assert estimate.model.fknee_hz == pytest.approx(0.02, rel=0.3)
    assert with_gap.model.fknee_hz == pytest.approx(without.model.fknee_hz, rel=0.3)
