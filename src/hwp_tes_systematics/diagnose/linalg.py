"""Whitened Fourier-domain least squares shared by the fit and the locate step.

For complex Fourier coefficients a_f, b_f and weights w_f = 1/S_f (S_f the expected
|noise_f|^2), the real inner product of the Whittle likelihood is

    <a, b> = sum_f 2 Re(a_f* b_f) w_f,

so that for a model sum_j p_j T_j the normal equations are G p = b with G_ij = <T_i, T_j>
and b_i = <T_i, R>, and chi^2 = <R - M, R - M>.
"""

from __future__ import annotations

import numpy as np


def realify(x: np.ndarray) -> np.ndarray:
    """Complex (..., Nf) -> real (..., 2 Nf): [Re, Im]."""
    return np.concatenate([x.real, x.imag], axis=-1)


def _as_real(x: np.ndarray) -> np.ndarray | None:
    """A C-contiguous complex array viewed as interleaved reals (..., 2 Nf), no copy."""
    if x.dtype == np.complex128 and x.flags.c_contiguous:
        return x.view(np.float64)
    return None


def cross(a: np.ndarray, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """sum_f 2 Re(a_i* b_j) w_f for a (Ka, Nf), b (Kb, Nf) or (Nf,) complex.

    Re(a* b) = Re a Re b + Im a Im b: one real matrix product over the interleaved
    (Re, Im) view of contiguous arrays (no copies of the real and imaginary parts).
    """
    a_real, b_real = _as_real(a), _as_real(b)
    if a_real is not None and b_real is not None:
        w2 = np.repeat(weights, 2)
        if b.ndim == 1:
            return 2.0 * (a_real @ (b_real * w2))
        return 2.0 * ((a_real * w2) @ b_real.T)
    if b.ndim == 1:
        return 2.0 * (a.real @ (b.real * weights) + a.imag @ (b.imag * weights))
    return 2.0 * ((a.real * weights) @ b.real.T + (a.imag * weights) @ b.imag.T)


def solve_normal(gram: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a = G^+ b with unit-diagonal scaling; returns (a, covariance G^+).

    Columns are scaled to a unit diagonal and eigenvalues below 1e-12 of the largest are
    dropped (pseudo-inverse): a parameter degenerate with others gets 0 and no gain.
    """
    k = gram.shape[0]
    a = np.zeros(k)
    cov = np.zeros((k, k))
    if k == 0:
        return a, cov
    diag = np.sqrt(np.clip(np.diag(gram), 0, None))
    good = diag > 0
    cov[~good, ~good] = np.inf
    if not good.any():
        return a, cov
    d = diag[good]
    normalised = gram[np.ix_(good, good)] / np.outer(d, d)
    evals, evecs = np.linalg.eigh(normalised)
    keep = evals > 1e-12 * evals.max()
    inverse = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    a[good] = inverse @ (rhs[good] / d) / d
    cov[np.ix_(good, good)] = inverse / np.outer(d, d)
    return a, cov


def whitened_lstsq(residual_f: np.ndarray, templates_f: np.ndarray, weights: np.ndarray):
    """Weighted least squares in the Fourier domain: (values, sigmas)."""
    gram = cross(templates_f, templates_f, weights)
    values, cov = solve_normal(gram, cross(templates_f, residual_f, weights))
    return values, np.sqrt(np.clip(np.diag(cov), 0, None))


def share_across_detectors(values, covariances, positions, scales):
    """Least squares with parameters shared by the detectors: p_k[positions] = s_k * r.

    ``values``, ``covariances``: each detector's unconstrained solution a_k and its
    covariance C_k (the detectors' fits are independent); ``positions`` (S,): where the
    shared parameters sit in each a_k; ``scales`` (n_det, S): s_k. With c_k = a_k[S] and
    P_k = C_k[S, S]^-1, the chi^2 of detector k rises by (c_k - s_k r)^T P_k (c_k - s_k r)
    when its other parameters are re-solved (a_k' = a_k + C_k[:, S] P_k (s_k r - c_k)),
    so the common value is

        r = F^-1 sum_k s_k P_k c_k,   F = sum_k s_k P_k s_k,   cov(r) = F^-1.

    Returns (the constrained a_k', their covariances with the shared block replaced by
    s_k cov(r) s_k, r, cov(r), the chi^2 the constraint costs).
    """
    positions = np.asarray(positions, dtype=int)
    n_shared = positions.size
    fisher = np.zeros((n_shared, n_shared))
    pulled = np.zeros(n_shared)
    precisions = []
    for a, cov, s in zip(values, covariances, scales, strict=True):
        block = cov[np.ix_(positions, positions)]
        finite = np.isfinite(np.diag(block))
        precision = np.zeros((n_shared, n_shared))
        if finite.any():
            precision[np.ix_(finite, finite)] = np.linalg.pinv(block[np.ix_(finite, finite)])
        precisions.append(precision)
        weighted = s[:, None] * precision * s[None, :]
        fisher += weighted
        pulled += s * (precision @ a[positions])
    cov_r = np.linalg.pinv(fisher)
    r = cov_r @ pulled
    new_values, new_covariances, cost = [], [], 0.0
    for a, cov, s, precision in zip(values, covariances, scales, precisions, strict=True):
        miss = s * r - a[positions]
        cost += float(miss @ precision @ miss)
        coupling = np.where(np.isfinite(cov[:, positions]), cov[:, positions], 0.0)
        new = a + coupling @ (precision @ miss)
        new[positions] = s * r
        new_cov = cov.copy()
        new_cov[np.ix_(positions, positions)] = s[:, None] * cov_r * s[None, :]
        new_values.append(new)
        new_covariances.append(new_cov)
    return new_values, new_covariances, r, cov_r, cost
