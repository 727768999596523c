"""The TES gain nonlinearity d_NL = (1 + g1 d + g2 d^2) d, with d in K_CMB.

The paper's model is the quadratic one (g2 = 0), as in litebird_sim's
``apply_quadratic_nonlin``; this vectorised form gives the same numbers without
its per-sample Python loop. Through it a pure HWPSS A cos(2 chi) acquires a DC
offset g1 A^2 / 2 and a 4 f_HWP line g1 A^2 / 2 (cos^2 x = (1 + cos 2x) / 2), and a
slow signal D cos(2 pi f_d t) mixes with it into lines at 2 f_HWP +- f_d of
amplitude g1 A D.

:func:`linearize` inverts the quadratic response with a measured g1_hat (the correction
a calibration from the data applies). With g1_hat = g1 it returns d to rounding; with a
calibration error delta = g1 - g1_hat it returns d + delta d^2 + O(g1 delta d^3): to first
order the corrected TOD carries the nonlinearity of g1 = delta, so the requirement on
sigma_g1 is a requirement on the calibration's error.
"""

from __future__ import annotations

import numpy as np


def apply_nonlinearity(tod_k: np.ndarray, g1_per_k, g2_per_k2=0.0) -> np.ndarray:
    """d_NL = d + g1 d^2 + g2 d^3 [K]; g1, g2 scalars or one per detector row."""
    g1 = np.asarray(g1_per_k, dtype=float)
    g2 = np.asarray(g2_per_k2, dtype=float)
    if tod_k.ndim == 2:
        g1 = g1.reshape(-1, 1) if g1.ndim else g1
        g2 = g2.reshape(-1, 1) if g2.ndim else g2
    return tod_k + g1 * tod_k**2 + g2 * tod_k**3


def linearize(tod_nl_k: np.ndarray, g1_hat_per_k) -> np.ndarray:
    """The d that a quadratic response of coefficient ``g1_hat`` [1/K] maps to d_NL:
    d = 2 d_NL / (1 + sqrt(1 + 4 g1_hat d_NL)) [K] (the root continuous at g1_hat = 0,
    free of its cancellation); ``g1_hat`` a scalar or one per detector row. Raises
    ValueError where 1 + 4 g1_hat d_NL < 0 (no real d: beyond the response's extremum)."""
    g1 = np.asarray(g1_hat_per_k, dtype=float)
    if tod_nl_k.ndim == 2 and g1.ndim:
        g1 = g1.reshape(-1, 1)
    discriminant = 1.0 + 4.0 * g1 * tod_nl_k
    if np.any(discriminant < 0):
        raise ValueError(
            "linearize: 1 + 4 g1 d_NL < 0 for some samples (g1 or the TOD beyond the "
            "quadratic response's extremum d = -1 / (2 g1))"
        )
    return 2.0 * tod_nl_k / (1.0 + np.sqrt(discriminant))
