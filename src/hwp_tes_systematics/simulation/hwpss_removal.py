"""Removal of the HWP synchronous signal's pure harmonics by template fitting.

Per detector and chunk, the least-squares fit of sum_n [a_n cos(n chi) + b_n sin(n chi)]
(n in ``harmonics``, default the 2f of the paper's HWPSS) is subtracted from the TOD:

    d -> d - D (D^T D)^-1 D^T d,      D = [cos(n chi), sin(n chi), ...]  (n_samples, 2 H).

This is a linear projection P (it commutes with the linear-in-g1 decomposition), it
removes a constant-amplitude HWPSS line but not the sky signal it modulates through
the nonlinearity (the 2 f_HWP +- f_sky sidebands and the 4 f_HWP leakage stay).
D^T D is close to (n/2) 1 for a uniformly rotating HWP, so the 2H x 2H normal
equations are well conditioned. With ``offset`` a constant column joins D, so that a
detector offset does not bias the harmonic fit (a constant is not orthogonal to
cos n chi over a non-integer number of turns: it would leave a small n f_HWP line);
the pipeline uses it when it removes baselines (:mod:`baselines`).
"""

from __future__ import annotations

import numpy as np


def harmonic_templates(hwp_angle_rad: np.ndarray, harmonics, offset: bool = False) -> np.ndarray:
    """D^T: (2 len(harmonics) [+ 1], n) rows cos(n chi), sin(n chi) [and a row of ones]."""
    templates = np.ones((2 * len(harmonics) + int(offset), np.size(hwp_angle_rad)))
    for index, harmonic in enumerate(harmonics):
        angle = harmonic * np.asarray(hwp_angle_rad, dtype=float)
        np.cos(angle, out=templates[2 * index])
        np.sin(angle, out=templates[2 * index + 1])
    return templates


def remove_hwp_harmonics(
    tod: np.ndarray,
    hwp_angle_rad: np.ndarray,
    harmonics=(2,),
    overwrite: bool = False,
    offset: bool = False,
):
    """d - P d: subtract the least-squares fit of the HWP harmonics (and with ``offset`` a
    constant) from each row of ``tod`` (any shape (..., n_samples); the fit is per row).
    ``overwrite`` reuses ``tod``'s memory (a C-contiguous float64 or float32 array, its
    dtype kept) for the result."""
    if len(harmonics) == 0 and not offset:
        return tod
    templates = harmonic_templates(hwp_angle_rad, harmonics, offset)  # D^T
    if not overwrite:
        tod = np.array(tod, dtype=float)
    rows = tod.reshape(-1, templates.shape[1])
    coefficients = np.linalg.solve(templates @ templates.T, templates @ rows.T)  # (2H, rows)
    for row, row_coefficients in zip(rows, coefficients.T):
        row -= row_coefficients @ templates
    return tod


def offset_residual(hwp_angle_rad: np.ndarray, harmonics=(2,)) -> np.ndarray:
    """u = 1 - P 1 (n,): a constant after the harmonic fit without offset. The fit with
    offset is the fit without it followed by the projection out of u,

        d - P_offset d = (d - P d) - c u,   c = <u, d> / <u, u>,

    so one pass of the fit without offset (and of any linear filter after it, applied
    to u too) gives both (:func:`tod_maps.filter_both_offsets`)."""
    return remove_hwp_harmonics(np.ones(np.size(hwp_angle_rad)), hwp_angle_rad, harmonics)
