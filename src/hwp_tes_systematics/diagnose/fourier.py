"""The diagnosis's real FFTs, on ducc0: ``rfft`` and ``irfft`` with scipy.fft's
conventions (no scaling forward, 1/n inverse; the inverse reads the first n/2 + 1
coefficients, zero-padding a shorter spectrum, and ignores the imaginary parts the
real transform cannot hold).

ducc0 is the FFT library healpy and litebird_sim already rest on; at a day of samples it
is 1.4-1.6 times faster than scipy's pocketfft on this project's machines
(``benchmarks/diagnose_benchmark.py`` prints the whole diagnosis's time), with the same
results to rounding (``tests/diagnose/test_fourier.py``).
"""

from __future__ import annotations

import ducc0
import numpy as np


def rfft(x: np.ndarray, axis: int = -1, workers: int = 1, out: np.ndarray | None = None):
    """X_f = sum_t x_t exp(-2 pi i f t / n), f = 0 .. n // 2, along ``axis`` (written into
    ``out`` if given: a complex array of the spectrum's shape)."""
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating) or (out is not None and x.dtype != np.float64):
        x = x.astype(np.float64)
    return ducc0.fft.r2c(x, axes=(axis % x.ndim,), nthreads=workers, out=out)


def irfft(spectrum: np.ndarray, n: int, axis: int = -1, workers: int = 1) -> np.ndarray:
    """x_t = (1/n) sum_f c_f Re(X_f exp(2 pi i f t / n)), the inverse of :func:`rfft` for
    n real samples (c_f = 1 at f = 0 and n/2, 2 elsewhere)."""
    spectrum = np.asarray(spectrum)
    axis = axis % spectrum.ndim
    wanted = n // 2 + 1
    have = spectrum.shape[axis]
    if have != wanted:  # as scipy: truncate, or zero-pad the highest frequencies
        if have > wanted:
            spectrum = np.take(spectrum, np.arange(wanted), axis=axis)
        else:
            pad = [(0, 0)] * spectrum.ndim
            pad[axis] = (0, wanted - have)
            spectrum = np.pad(spectrum, pad)
    if not np.iscomplexobj(spectrum):
        spectrum = spectrum.astype(np.complex128)
    return ducc0.fft.c2r(
        spectrum, axes=(axis,), lastsize=n, forward=False, inorm=2, nthreads=workers
    )
