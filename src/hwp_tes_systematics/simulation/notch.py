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

import functools

import ducc0
import numpy as np

DEFAULT_WIDTH_DIVISOR = 100.0  # delta f = 4 f_HWP / 100 (paper)


def notch_width_hz(f_hwp_hz: float, width_divisor: float = DEFAULT_WIDTH_DIVISOR) -> float:
    """delta f = 4 f_HWP / width_divisor [Hz] (``notch.width_divisor`` of the config)."""
    return 4.0 * f_hwp_hz / width_divisor


def notch_edges_hz(f_hwp_hz: float, delta_f_hz: float | None = None) -> tuple[float, ...]:
    """(f1, f2, f3, f4) around 4 f_HWP; delta f defaults to 4 f_HWP / 100."""
    center_hz = 4.0 * f_hwp_hz
    if delta_f_hz is None:
        delta_f_hz = notch_width_hz(f_hwp_hz)
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
    """Filter along the last axis: irfft(F(f) rfft(tod)) (see :func:`apply_transfer`)."""
    return apply_transfer(
        tod,
        lambda n_fft: _transfer_on_rfft_grid(n_fft, sampling_rate_hz, f_hwp_hz, delta_f_hz),
        workers,
    )


def apply_transfer(tod: np.ndarray, transfer_on_grid, workers: int = 1) -> np.ndarray:
    """irfft(T(f) rfft(tod)) along the last axis, zero-padded to a fast FFT length
    (ducc0's FFT, ``workers`` threads; all rows in one call). ``transfer_on_grid(n_fft)``
    gives T at the rfft frequencies k f_s / n_fft, k = 0 .. n_fft // 2. A float32 TOD is
    filtered in single precision (half the time), any other in float64."""
    tod = np.asarray(tod)
    if tod.dtype != np.float32:
        tod = np.asarray(tod, dtype=np.float64)
    n_samples = tod.shape[-1]
    n_fft = ducc0.fft.good_size(n_samples, True)
    if n_fft != n_samples:
        padded = np.zeros((*tod.shape[:-1], n_fft), dtype=tod.dtype)
        padded[..., :n_samples] = tod
        tod = padded
    axis = (tod.ndim - 1,)
    spectrum = ducc0.fft.r2c(tod, axes=axis, nthreads=workers)
    del tod
    spectrum *= transfer_on_grid(n_fft)
    filtered = ducc0.fft.c2r(  # the spectrum is scratch: overwriting it halves the c2r time
        spectrum,
        axes=axis,
        lastsize=n_fft,
        forward=False,
        inorm=2,
        nthreads=workers,
        allow_overwriting_input=True,
    )
    return filtered[..., :n_samples]


@functools.lru_cache(maxsize=8)
def _transfer_on_rfft_grid(n_fft, sampling_rate_hz, f_hwp_hz, delta_f_hz) -> np.ndarray:
    """F(f) at the rfft frequencies k f_s / n_fft, k = 0 .. n_fft // 2 (read-only)."""
    freqs_hz = np.arange(n_fft // 2 + 1) * (sampling_rate_hz / n_fft)
    transfer = notch_transfer(freqs_hz, f_hwp_hz, delta_f_hz)
    transfer.flags.writeable = False
    return transfer


def margin_samples(sampling_rate_hz: float, margin_s: float) -> int:
    """Number of samples simulated beyond each chunk edge for the filter."""
    return int(np.ceil(margin_s * sampling_rate_hz))


def chunk_span(
    first_sample: int, n_samples: int, sampling_rate_hz: float, margin_s: float
) -> tuple[int, int, slice]:
    """The samples to simulate for a chunk: at least ``margin_s`` beyond each edge,
    widened so the total is a fast FFT length (no zero padding in ``apply_notch``).

    Returns (first simulated sample, number simulated, slice of the chunk within them).
    """
    margin = margin_samples(sampling_rate_hz, margin_s)
    n_total = ducc0.fft.good_size(n_samples + 2 * margin, True)
    before = margin + (n_total - n_samples - 2 * margin) // 2
    return first_sample - before, n_total, slice(before, before + n_samples)


def filter_chunk_with_margins(
    tod_with_margins: np.ndarray,
    inner: slice,
    sampling_rate_hz: float,
    f_hwp_hz: float,
    delta_f_hz: float | None = None,
    workers: int = 1,
) -> np.ndarray:
    """Filter a chunk simulated with margins on each side; keep the ``inner`` samples."""
    filtered = apply_notch(tod_with_margins, sampling_rate_hz, f_hwp_hz, delta_f_hz, workers)
    return filtered[..., inner]
