"""The 4 f_HWP notch filter of the paper, applied in Fourier space, chunk by chunk.

    F(f) = 1                                          f <= f1
         = 0.5 (1 + cos(pi (f - f1) / (f2 - f1)))     f1 < f <= f2
         = 0                                          f2 < f <= f3
         = 0.5 (1 - cos(pi (f - f3) / (f4 - f3)))     f3 < f <= f4
         = 1                                          f > f4

with f1,4 = 4 f_HWP -+ 2 delta f, f2,3 = 4 f_HWP -+ delta f, delta f = 4 f_HWP / 100.

A chunk of TOD is filtered with a margin of samples on each side, simulated
beyond the chunk's edges, that absorbs the circular wrap-around of the FFT; the
margins are then dropped, so no chunk-boundary artefact reaches the maps.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

DEFAULT_WIDTH_DIVISOR = 100.0  # delta f = 4 f_HWP / 100 (paper)


def notch_edges_hz(f_hwp_hz: float, delta_f_hz: float | None = None) -> tuple[float, ...]:
    """(f1, f2, f3, f4) around 4 f_HWP; delta f defaults to 4 f_HWP / 100."""
    center_hz = 4.0 * f_hwp_hz
    if delta_f_hz is None:
        delta_f_hz = center_hz / DEFAULT_WIDTH_DIVISOR
    if not delta_f_hz > 0:
        raise ValueError(f"notch delta_f_hz = {delta_f_hz}: expected a width > 0 Hz")
    return (
        center_hz - 2 * delta_f_hz,
        center_hz - delta_f_hz,
        center_hz + delta_f_hz,
        center_hz + 2 * delta_f_hz,
    )


def notch_transfer(freqs_hz, f_hwp_hz: float, delta_f_hz: float | None = None) -> np.ndarray:
    """F(f) of the paper (see the module docstring); |f| is used for negative frequencies."""
    f1, f2, f3, f4 = notch_edges_hz(f_hwp_hz, delta_f_hz)
    f = np.abs(np.asarray(freqs_hz, dtype=float))
    transfer = np.ones_like(f)
    falling = (f > f1) & (f <= f2)
    transfer[falling] = 0.5 * (1 + np.cos(np.pi * (f[falling] - f1) / (f2 - f1)))
    transfer[(f > f2) & (f <= f3)] = 0.0
    rising = (f > f3) & (f <= f4)
    transfer[rising] = 0.5 * (1 - np.cos(np.pi * (f[rising] - f3) / (f4 - f3)))
    return transfer


def apply_notch(
    tod: np.ndarray,
    sampling_rate_hz: float,
    f_hwp_hz: float,
    delta_f_hz: float | None = None,
    workers: int = 1,
) -> np.ndarray:
    """Filter along the last axis: irfft(F(f) rfft(tod)), zero-padded to a fast FFT length."""
    n_samples = tod.shape[-1]
    n_fft = scipy.fft.next_fast_len(n_samples, real=True)
    spectrum = scipy.fft.rfft(tod, n=n_fft, axis=-1, workers=workers)
    freqs_hz = scipy.fft.rfftfreq(n_fft, d=1.0 / sampling_rate_hz)
    spectrum *= notch_transfer(freqs_hz, f_hwp_hz, delta_f_hz)
    return scipy.fft.irfft(spectrum, n=n_fft, axis=-1, workers=workers)[..., :n_samples]


def margin_samples(sampling_rate_hz: float, margin_s: float) -> int:
    """Number of samples simulated beyond each chunk edge for the filter."""
    return int(np.ceil(margin_s * sampling_rate_hz))


def filter_chunk_with_margins(
    tod_with_margins: np.ndarray,
    margin: int,
    sampling_rate_hz: float,
    f_hwp_hz: float,
    delta_f_hz: float | None = None,
    workers: int = 1,
) -> np.ndarray:
    """Filter a chunk simulated with ``margin`` extra samples on each side; drop the margins."""
    filtered = apply_notch(tod_with_margins, sampling_rate_hz, f_hwp_hz, delta_f_hz, workers)
    return filtered[..., margin : tod_with_margins.shape[-1] - margin]
