"""The TES gain nonlinearity d_NL = (1 + g1 d + g2 d^2) d, with d in K_CMB.

The paper's model is the quadratic one (g2 = 0), as in litebird_sim's
``apply_quadratic_nonlin``; this vectorised form gives the same numbers without
its per-sample Python loop. Through it a pure HWPSS A cos(2 chi) acquires a DC
offset g1 A^2 / 2 and a 4 f_HWP line g1 A^2 / 2 (cos^2 x = (1 + cos 2x) / 2), and a
slow signal D cos(2 pi f_d t) mixes with it into lines at 2 f_HWP +- f_d of
amplitude g1 A D.
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
