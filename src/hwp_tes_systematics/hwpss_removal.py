"""Removal of the HWP synchronous signal's pure harmonics by template fitting.

Per detector and chunk, the least-squares fit of sum_n [a_n cos(n chi) + b_n sin(n chi)]
(n in ``harmonics``, default the 2f of the paper's HWPSS) is subtracted from the TOD.
This is a linear projection P (it commutes with the linear-in-g1 decomposition), it
removes a constant-amplitude HWPSS line but not the sky signal it modulates through
the nonlinearity (the 2 f_HWP +- f_sky sidebands and the 4 f_HWP leakage stay).
"""

from __future__ import annotations

import numpy as np


def harmonic_design(hwp_angle_rad: np.ndarray, harmonics) -> np.ndarray:
    """(n, 2 len(harmonics)) columns cos(n chi), sin(n chi)."""
    columns = []
    for harmonic in harmonics:
        columns += [np.cos(harmonic * hwp_angle_rad), np.sin(harmonic * hwp_angle_rad)]
    return np.column_stack(columns)


def remove_hwp_harmonics(tod: np.ndarray, hwp_angle_rad: np.ndarray, harmonics=(2,)):
    """d - P d: subtract the least-squares fit of the HWP harmonics from each row of ``tod``."""
    if len(harmonics) == 0:
        return tod
    design = harmonic_design(hwp_angle_rad, harmonics)
    coefficients, *_ = np.linalg.lstsq(design, np.atleast_2d(tod).T, rcond=None)
    return tod - (design @ coefficients).T.reshape(tod.shape)
