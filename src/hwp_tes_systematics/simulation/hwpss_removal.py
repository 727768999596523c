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

import numba
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
    templates: np.ndarray | None = None,
):
    """d - P d: subtract the least-squares fit of the HWP harmonics (and with ``offset`` a
    constant) from each row of ``tod`` (any shape (..., n_samples); the fit is per row).
    ``overwrite`` reuses ``tod``'s memory (a C-contiguous float64 or float32 array, its
    dtype kept) for the result. ``templates``: D^T of :func:`harmonic_templates` for
    these angles, harmonics and offset, if already computed (a chunk's filters share
    them). The projections D^T d are summed in float64 whatever the TOD's dtype."""
    if len(harmonics) == 0 and not offset:
        return tod
    if templates is None:
        templates = harmonic_templates(hwp_angle_rad, harmonics, offset)  # D^T
    expected = (2 * len(harmonics) + int(offset), np.size(hwp_angle_rad))
    if templates.shape != expected:
        raise ValueError(
            f"harmonic templates of shape {templates.shape}: expected {expected} for "
            f"harmonics {tuple(harmonics)}, offset {offset}"
        )
    if not overwrite:
        tod = np.array(tod, dtype=float)
    rows = tod.reshape(-1, templates.shape[1])
    inverse_gram = np.linalg.inv(templates @ templates.T)  # (D^T D)^-1, 2H [+1] square
    _subtract_fit(rows, np.ascontiguousarray(templates), inverse_gram)
    return tod


# samples per block of _subtract_fit: the templates' block stays in the L1 cache while
# every row passes through it
_FIT_BLOCK = 1024


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _subtract_fit(rows, templates, inverse_gram):  # pragma: no cover (compiled)
    """rows -= c D^T, c = D^T row (D^T D)^-1 for every row, in place: two sweeps over
    the samples in blocks (the projections of all rows, then the subtraction), with no
    temporary of a row's size. Projections summed in float64 (the sum's order is
    numba's: the fit equals numpy's to rounding, ~1e-13 relative over a day)."""
    n_templates, n_samples = templates.shape
    n_rows = rows.shape[0]
    projections = np.zeros((n_rows, n_templates))
    for start in range(0, n_samples, _FIT_BLOCK):
        stop = min(start + _FIT_BLOCK, n_samples)
        for r in range(n_rows):
            row = rows[r]
            for j in range(n_templates):
                template = templates[j]
                total = 0.0
                for t in range(start, stop):
                    total += template[t] * np.float64(row[t])
                projections[r, j] += total
    coefficients = projections @ inverse_gram.T
    for start in range(0, n_samples, _FIT_BLOCK):
        stop = min(start + _FIT_BLOCK, n_samples)
        for r in range(n_rows):
            row = rows[r]
            for j in range(n_templates):
                coefficient = coefficients[r, j]
                template = templates[j]
                for t in range(start, stop):
                    row[t] -= coefficient * template[t]


def offset_residual(hwp_angle_rad: np.ndarray, harmonics=(2,), templates=None) -> np.ndarray:
    """u = 1 - P 1 (n,): a constant after the harmonic fit without offset. The fit with
    offset is the fit without it followed by the projection out of u,

        d - P_offset d = (d - P d) - c u,   c = <u, d> / <u, u>,

    so one pass of the fit without offset (and of any linear filter after it, applied
    to u too) gives both (:func:`tod_filter.filter_both_offsets`). ``templates``: as in
    :func:`remove_hwp_harmonics` (those without offset)."""
    ones = np.ones(np.size(hwp_angle_rad))
    return remove_hwp_harmonics(ones, hwp_angle_rad, harmonics, templates=templates)
