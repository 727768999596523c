"""The 4 f_HWP notch filter: transfer function, line removal, chunk edges."""

import numpy as np
import pytest

from hwp_tes_systematics.simulation.notch import (
    apply_notch,
    filter_chunk_with_margins,
    margin_samples,
    notch_edges_hz,
    notch_transfer,
)

SAMPLING_RATE_HZ = 31.0
F_HWP_HZ = 39.0 / 60.0  # MFT


def test_transfer_function_shape():
    f1, f2, f3, f4 = notch_edges_hz(F_HWP_HZ)
    delta_f = 4 * F_HWP_HZ / 100
    assert (f2 - f1, f4 - f3) == pytest.approx((delta_f, delta_f))
    transfer = notch_transfer(
        np.array([0.0, f1, (f1 + f2) / 2, f2, 4 * F_HWP_HZ, f3, (f3 + f4) / 2, f4, 10.0]), F_HWP_HZ
    )
    np.testing.assert_allclose(transfer, [1, 1, 0.5, 0, 0, 0, 0.5, 1, 1], atol=1e-12)


def time_axis(duration_s):
    return np.arange(int(duration_s * SAMPLING_RATE_HZ)) / SAMPLING_RATE_HZ


def test_pure_4f_line_is_removed():
    t = time_axis(3600)
    line = 0.3 * np.cos(2 * np.pi * 4 * F_HWP_HZ * t + 0.4)
    filtered = apply_notch(line, SAMPLING_RATE_HZ, F_HWP_HZ)
    middle = slice(len(t) // 4, 3 * len(t) // 4)  # away from the FFT's circular edges
    assert np.abs(filtered[middle]).max() < 1e-6 * 0.3


@pytest.mark.parametrize("sign", [-1, 1])
def test_line_three_widths_away_passes_unchanged(sign):
    delta_f = 4 * F_HWP_HZ / 100
    t = time_axis(3600)
    line = np.sin(2 * np.pi * (4 * F_HWP_HZ + sign * 3 * delta_f) * t)
    filtered = apply_notch(line, SAMPLING_RATE_HZ, F_HWP_HZ)
    middle = slice(len(t) // 4, 3 * len(t) // 4)
    np.testing.assert_allclose(filtered[middle], line[middle], atol=1e-6)


def test_chunked_filtering_with_margins_equals_continuous_filtering():
    rng = np.random.default_rng(1)
    t = time_axis(4 * 3600)
    tod = rng.normal(size=t.size) + np.cos(2 * np.pi * 4 * F_HWP_HZ * t) + 1e-3 * t
    continuous = apply_notch(tod, SAMPLING_RATE_HZ, F_HWP_HZ)
    margin = margin_samples(SAMPLING_RATE_HZ, 1200.0)
    chunk = int(1800 * SAMPLING_RATE_HZ)
    start = 2 * chunk
    filtered = filter_chunk_with_margins(
        tod[start - margin : start + chunk + margin],
        slice(margin, margin + chunk),
        SAMPLING_RATE_HZ,
        F_HWP_HZ,
    )
    assert filtered.shape == (chunk,)
    error = np.abs(filtered - continuous[start : start + chunk]).max() / continuous.std()
    assert error < 1e-6


def test_filter_acts_on_each_detector_row():
    t = time_axis(3600)
    tod = np.vstack([np.cos(2 * np.pi * 4 * F_HWP_HZ * t), np.ones_like(t)])
    filtered = apply_notch(tod, SAMPLING_RATE_HZ, F_HWP_HZ)
    assert filtered.shape == tod.shape
    middle = slice(len(t) // 4, 3 * len(t) // 4)
    assert np.abs(filtered[0, middle]).max() < 1e-6
    np.testing.assert_allclose(filtered[1, middle], 1.0, atol=1e-6)
