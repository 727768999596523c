"""Where the recording differs from the simulation: frequency, HWP angle, time and sky.

All on the residual r = recording - d_nom (flagged samples masked), against the noise
model P(f) of the residual (:mod:`.noise`).

Frequency (:func:`find_lines`). Blackman-Harris-windowed periodogram normalised by the
noise, z_f = |X_f|^2 / (P(f) f_s/2 sum w^2), exponentially distributed with mean 1 for
noise. The largest z above the threshold ln(N_f / p) (p = the one-sided 5 sigma tail
probability, N_f frequencies searched: a look-elsewhere corrected 5 sigma) is a line:
its frequency is refined by a parabola through log z, its amplitude and phase fitted by
least squares (a cos + b sin at that frequency, sigma_a = sqrt(P(f) / T_valid)), the
sinusoid is subtracted and the search repeated (CLEAN); a peak is searched only once
(a non-sinusoidal component, e.g. a drifting line, leaves power CLEAN cannot remove) and
fits below 5 sigma are not reported. The line is fitted with a slowly varying amplitude,
sum_{j<=3} P_j(x) (a_j cos + b_j sin), so that a drifting line (gain or HWP temperature
drift) is one line with a "modulation", not a comb of lines. Each line is named by the
simplest combination n f_HWP + m f_spin + k f_prec (0 <= n <= 8, |m|, |k| <= 3; spin
and precession terms only when resolved, >= 2 frequency bins) within 3 bins
(complexity (n > 0) + |m| + |k| first, then distance), and then fitted AT that
combination's frequency ("offset_hz" is how far the periodogram peak was). The
dipole sits at f_spin and its precession sidebands, so "2 f_HWP +- f_spin" are the
HWPSS x dipole intermodulation lines. Excess bands: the mean of |R_f|^2 / S_nom,f over
logarithmic bands (line bins excluded); for noise it is the mean of m unit exponentials,
Gamma(m, 1/m), whose tail (not the Gaussian 1 +- 1/sqrt(m), which at m ~ 20 calls a
4 sigma excess 5 sigma) gives the band's probability, corrected for the bands tested.

HWP angle (:func:`hwp_profile`). Residual averaged in 64 bins of chi (per detector),
and the amplitudes of n = 1..8 harmonics A_n cos(n chi - phi_n) by least squares on
all valid samples, sigma = sigma_white sqrt(2 / N_valid).

Time. Transients (:func:`find_transients`): the residual whitened by sqrt(S_white / S_f)
is thresholded at ``threshold_sigma`` robust standard deviations (1.4826 x the median
absolute deviation) and each group of hits fitted as A exp(-(t - t0)/tau). Drifts
(:func:`drifts`): whitened least-squares (Fourier domain, weights 1/S_f, so the 1/f noise
is accounted for) of the residual on P1(x) (offset slope), on [1, P1] x cos 2(chi - theta)
and sin (2f amplitude drift) and on [1, P1] x D (dipole gain drift), with uncertainties.

Sky (:func:`sky_residual`). Residual binned in Galactic pixels (nside 32, or the sky
map's if coarser); Pearson correlation (Fisher z = atanh(r) sqrt(N_pix - 3)) and the
least-squares coefficients of the residual map on the binned nominal intensity and
dipole maps.
"""

from .drifts import dc_offset, drifts
from .frequency import (
    FIVE_SIGMA_P,
    MAX_HARMONIC,
    MAX_LINES,
    Line,
    excess_bands,
    find_lines,
    identify,
    line_at,
    modulated_line_fit,
    p_to_sigma,
    sinusoid_fit,
)
from .hwp_angle import HWP_BINS, Harmonic, hwp_profile
from .sky import SKY_NSIDE, bin_map, sky_residual
from .step import Mismatch, locate

__all__ = [
    "FIVE_SIGMA_P",
    "HWP_BINS",
    "MAX_HARMONIC",
    "MAX_LINES",
    "SKY_NSIDE",
    "Harmonic",
    "Line",
    "Mismatch",
    "bin_map",
    "dc_offset",
    "drifts",
    "excess_bands",
    "find_lines",
    "hwp_profile",
    "identify",
    "line_at",
    "locate",
    "modulated_line_fit",
    "p_to_sigma",
    "sinusoid_fit",
    "sky_residual",
]
