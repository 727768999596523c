"""Spectral tools for TOD: amplitude spectra and the amplitude of a line of known frequency."""

from __future__ import annotations

import numpy as np
import scipy.fft


def amplitude_spectrum(tod: np.ndarray, sampling_rate_hz: float, window: str = "hann"):
    """One-sided amplitude spectrum |X(f)| scaled so a sinusoid of amplitude A peaks at ~A.

    Returns (freqs_hz, amplitude); a Hann window trades resolution for leakage.
    """
    n_samples = tod.shape[-1]
    taper = np.hanning(n_samples) if window == "hann" else np.ones(n_samples)
    spectrum = scipy.fft.rfft(tod * taper, axis=-1)
    amplitude = 2.0 * np.abs(spectrum) / taper.sum()
    return scipy.fft.rfftfreq(n_samples, d=1.0 / sampling_rate_hz), amplitude


def line_amplitude(tod: np.ndarray, times_s: np.ndarray, freq_hz: float) -> tuple[float, float]:
    """Least-squares amplitude and phase of a + A cos(2 pi f t + phi) in a 1-D TOD.

    Returns (A, phi) with A >= 0; a constant is fitted alongside.
    """
    phase = 2 * np.pi * freq_hz * times_s
    design = np.column_stack([np.ones_like(times_s), np.cos(phase), np.sin(phase)])
    coefficients, *_ = np.linalg.lstsq(design, tod, rcond=None)
    _, cosine, sine = coefficients
    return float(np.hypot(cosine, sine)), float(np.arctan2(-sine, cosine))
