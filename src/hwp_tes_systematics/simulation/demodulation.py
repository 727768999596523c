"""HWP demodulation plus a low-pass: the map-maker of sotodlib's ``demod_tod`` and
TOAST's ``Demodulate``, beside the binned solve of :mod:`mapmaking`.

A sample of detector k is d = I + rho (Q cos 2 alpha + U sin 2 alpha) with
2 alpha = 4 chi + beta, chi the HWP angle and beta = 2 psi - 2 theta_k (psi: the
pointing's polarisation angle, slow). With L a low-pass of cut-off f_c below 2 f_HWP,
and a sky whose TOD band lies below f_c,

    L(d)            = I,
    d_Q = L(2 d cos 4 chi) = rho (Q cos beta + U sin beta),
    d_U = L(2 d sin 4 chi) = rho (U cos beta - Q sin beta),

so each sample measures Q and U on its own, and the least-squares map of a pixel is

    I_p = sum w L(d) / sum w,
    Q_p = sum w rho (cos beta d_Q - sin beta d_U) / sum w rho^2,
    U_p = sum w rho (sin beta d_Q + cos beta d_U) / sum w rho^2,

whatever HWP angles the pixel's samples had. What the binned solve turns into Q/U
through an incomplete HWP-angle coverage (a detector offset, the DC term g1 A_2^2 / 2
of the nonlinearity) sits at 4 f_HWP in d_Q, d_U and the low-pass removes it; what
sits at 4 f_HWP in d (the nonlinearity's 4f line, what the notch leaves of it) is a
constant there, in the HWP frame, and reaches the map rotated by beta.
"""

from __future__ import annotations

import ducc0
import healpy as hp
import numba
import numpy as np

from .notch import apply_transfer

# the low-pass's cut-off and half transition width, in units of f_HWP: sotodlib's
# demod_tod default for a 2 Hz HWP (1.9 Hz, 0.1 Hz wide), scaled (assumption)
CUTOFF_OVER_F_HWP = 0.95
HALF_TRANSITION_OVER_F_HWP = 0.05


def lowpass_transfer(freqs_hz, cutoff_hz: float, half_width_hz: float) -> np.ndarray:
    """L(f) = 1 below f_c - w, (1 + cos(pi x)) / 2 with x = (f - f_c + w) / 2w down to 0
    at f_c + w, 0 above (|f| used)."""
    f = np.abs(np.asarray(freqs_hz, dtype=float))
    x = np.clip((f - (cutoff_hz - half_width_hz)) / (2 * half_width_hz), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def decimation_factor(sampling_rate_hz: float, f_hwp_hz: float) -> int:
    """The sample stride D at which the demodulated streams are kept: floor(f_s / 4 f_HWP),
    at least 1. The low-pass leaves nothing above f_HWP, so streams sampled at f_s / D
    (Nyquist >= 2 f_HWP) are the same band-limited signals (as sotodlib's demodulation then
    downsampling), and their binning and inverse transforms cost 1 / D."""
    return max(1, int(sampling_rate_hz // (4.0 * f_hwp_hz)))


def demodulate(
    tod: np.ndarray,
    hwp_angle_rad: np.ndarray,
    sampling_rate_hz: float,
    f_hwp_hz: float,
    workers=1,
    decimation: int = 1,
) -> np.ndarray:
    """(L d, L(2 d cos 4 chi), L(2 d sin 4 chi)) stacked on a new first axis, for a TOD
    (any leading shape, time last, with margins: the low-pass wraps around), at samples
    0, D, 2 D, ... (D = ``decimation``; the low-pass must end below f_s / 2 D); a float32
    TOD (the calibration TODs) is demodulated in single precision, any other in float64."""
    cutoff_hz = CUTOFF_OVER_F_HWP * f_hwp_hz
    half_width_hz = HALF_TRANSITION_OVER_F_HWP * f_hwp_hz
    if decimation > 1 and cutoff_hz + half_width_hz > sampling_rate_hz / (2 * decimation):
        raise ValueError(
            f"demodulation decimation {decimation}: the low-pass reaches {cutoff_hz + half_width_hz:.3g} "
            f"Hz, above the decimated Nyquist frequency {sampling_rate_hz / (2 * decimation):.3g} Hz"
        )
    tod = np.asarray(tod)
    dtype = np.float32 if tod.dtype == np.float32 else np.float64
    tod = tod.astype(dtype, copy=False)
    streams = np.empty((3, *tod.shape), dtype=dtype)
    streams[0] = tod
    np.multiply(tod, (2.0 * np.cos(4.0 * hwp_angle_rad)).astype(dtype), out=streams[1])
    np.multiply(tod, (2.0 * np.sin(4.0 * hwp_angle_rad)).astype(dtype), out=streams[2])

    def transfer_on_grid(n_fft):
        return lowpass_transfer(
            np.arange(n_fft // 2 + 1) * (sampling_rate_hz / n_fft), cutoff_hz, half_width_hz
        )

    if decimation == 1:
        return apply_transfer(streams, transfer_on_grid, workers)
    return _lowpass_decimated(streams, transfer_on_grid, decimation, workers)


def _lowpass_decimated(streams, transfer_on_grid, decimation: int, workers: int) -> np.ndarray:
    """irfft(L rfft(x)) at samples 0, D, 2 D, ...: the forward transform at a length
    n_fft divisible by D, the inverse at n_fft / D from the spectrum's first n_fft / 2 D + 1
    bins (L is zero beyond them), so the result is the low-passed TOD itself, decimated."""
    n_samples = streams.shape[-1]
    n_short = ducc0.fft.good_size(-(-n_samples // decimation), True)
    n_fft = n_short * decimation
    padded = np.zeros((*streams.shape[:-1], n_fft), dtype=streams.dtype)
    padded[..., :n_samples] = streams
    axis = (padded.ndim - 1,)
    spectrum = ducc0.fft.r2c(padded, axes=axis, nthreads=workers)
    del padded
    low = transfer_on_grid(n_fft)[: n_short // 2 + 1].astype(streams.dtype)
    kept = spectrum[..., : n_short // 2 + 1] * low
    del spectrum
    decimated = ducc0.fft.c2r(
        kept, axes=axis, lastsize=n_short, forward=False, inorm=0, nthreads=workers
    )
    decimated *= 1.0 / n_fft  # the inverse of the full-length transform
    return decimated[..., : -(-n_samples // decimation)]


class DemodulatedEquations:
    """Accumulates sum w, sum w rho^2 and the three sums of the module docstring per pixel,
    for several TODs given as demodulated streams."""

    def __init__(self, nside: int, n_tods: int):
        self.nside = nside
        self.npix = hp.nside2npix(nside)
        self.n_tods = n_tods
        self.weight = np.zeros(self.npix)  # sum w
        self.pol_weight = np.zeros(self.npix)  # sum w rho^2
        self.rhs = np.zeros((n_tods, 3, self.npix))
        self.hits = np.zeros(self.npix, dtype=np.int64)

    def add(
        self,
        pixels,
        cos_2alpha,
        sin_2alpha,
        hwp_angle_rad,
        weights,
        pol_efficiency,
        streams,
        tod_detectors=None,
    ) -> None:
        """Add samples: pixels, angles (n_det, n), hwp_angle_rad (n,); weights,
        pol_efficiency (n_det,); streams: n_tods arrays (3, n_det, n) from
        :func:`demodulate`; ``tod_detectors[i]``, if not None, the only detector of TOD i."""
        if len(streams) != self.n_tods:
            raise ValueError(f"expected {self.n_tods} demodulated TODs, got {len(streams)}")
        if tod_detectors is None:
            tod_detectors = [None] * self.n_tods
        weights = np.ascontiguousarray(weights, dtype=np.float64)
        rho = np.ascontiguousarray(pol_efficiency, dtype=np.float64)
        cos_4chi = np.cos(4.0 * hwp_angle_rad)
        sin_4chi = np.sin(4.0 * hwp_angle_rad)
        _add_weights(pixels, weights, rho, self.weight, self.pol_weight, self.hits)
        for index, stream in enumerate(streams):
            owner = -1 if tod_detectors[index] is None else int(tod_detectors[index])
            _add_rotated(
                pixels,
                cos_2alpha,
                sin_2alpha,
                cos_4chi,
                sin_4chi,
                weights,
                rho,
                stream,
                owner,
                self.rhs[index],
            )

    def reorder(self, source: np.ndarray) -> None:
        """Pixel p takes the numbers of pixel ``source[p]`` (a change of ordering)."""
        self.weight = self.weight[source]
        self.pol_weight = self.pol_weight[source]
        self.rhs = self.rhs[:, :, source]
        self.hits = self.hits[source]

    def solve(self) -> np.ndarray:
        """(n_tods, 3, npix) I, Q, U maps; pixels without samples are UNSEEN."""
        maps = np.full((self.n_tods, 3, self.npix), hp.UNSEEN)
        seen = self.hits > 0
        maps[:, 0, seen] = self.rhs[:, 0, seen] / self.weight[seen]
        maps[:, 1:, seen] = self.rhs[:, 1:, seen] / self.pol_weight[seen]
        return maps


@numba.njit(cache=True, nogil=True)
def _add_weights(pixels, weights, rho, weight, pol_weight, hits):
    for det in range(pixels.shape[0]):
        for t in range(pixels.shape[1]):
            p = pixels[det, t]
            hits[p] += 1
            weight[p] += weights[det]
            pol_weight[p] += weights[det] * rho[det] * rho[det]


@numba.njit(cache=True, nogil=True)
def _add_rotated(
    pixels, cos_2alpha, sin_2alpha, cos_4chi, sin_4chi, weights, rho, stream, owner, rhs
):
    """rhs[:, p] += w [L d, rho (c d_Q - s d_U), rho (s d_Q + c d_U)], (c, s) = (cos, sin)
    beta from 2 alpha - 4 chi by angle subtraction."""
    for det in range(pixels.shape[0]):
        if owner >= 0 and det != owner:
            continue
        w = weights[det]
        for t in range(pixels.shape[1]):
            p = pixels[det, t]
            c = cos_2alpha[det, t] * cos_4chi[t] + sin_2alpha[det, t] * sin_4chi[t]
            s = sin_2alpha[det, t] * cos_4chi[t] - cos_2alpha[det, t] * sin_4chi[t]
            d_q = stream[1, det, t]
            d_u = stream[2, det, t]
            rhs[0, p] += w * stream[0, det, t]
            rhs[1, p] += w * rho[det] * (c * d_q - s * d_u)
            rhs[2, p] += w * rho[det] * (s * d_q + c * d_u)
