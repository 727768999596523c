"""Binned map-making from normal equations accumulated chunk by chunk.

Each sample of detector k sees the pixel p through the row a = [1, rho cos 2 alpha,
rho sin 2 alpha] (alpha = 2 chi - theta_det + psi). Weighting each detector by
w_k = 1 / sigma_k^2, the binned map of pixel p solves

    (sum a^T w a) m_p = sum a^T w d,

the same estimator as litebird_sim's ``make_binned_map``. The 3 x 3 matrix does
not depend on the TOD, so one accumulation serves any number of TODs: the
no-systematics map and each detector's nonlinearity template. Memory holds one
chunk of TOD plus (6 + 3 x n_tods) numbers per pixel.
"""

from __future__ import annotations

import healpy as hp
import numba
import numpy as np

# the six independent entries of the symmetric 3x3 matrix, as (row, column)
MATRIX_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


class NormalEquations:
    """Accumulates sum a^T w a (per pixel) and sum a^T w d for several TODs.

    Stored pixel-major (``pixel_matrix`` (npix, 6), ``pixel_rhs`` (npix, n_tods, 3)), so
    that a sample touches one pixel's numbers for every TOD at once: at nside 512 the
    maps no longer fit the caches and a TOD-major layout cost a cache miss per TOD and
    Stokes parameter. ``matrix`` (6, npix) and ``rhs`` (n_tods, 3, npix) are views of
    them. Each number receives the same additions in the same order as one TOD at a
    time would give it, so the result does not depend on the layout."""

    def __init__(self, nside: int, n_tods: int):
        self.nside = nside
        self.npix = hp.nside2npix(nside)
        self.n_tods = n_tods
        self.pixel_matrix = np.zeros((self.npix, 6))
        self.pixel_rhs = np.zeros((self.npix, n_tods, 3))
        self.hits = np.zeros(self.npix, dtype=np.int64)

    def subset(self, tods) -> NormalEquations:
        """The equations of the TODs ``tods`` (indices) alone: matrix and hits shared (not
        copied), right-hand sides copied."""
        chosen = list(tods)
        subset = NormalEquations.__new__(NormalEquations)
        subset.nside, subset.npix, subset.n_tods = self.nside, self.npix, len(chosen)
        subset.pixel_matrix, subset.hits = self.pixel_matrix, self.hits
        subset.pixel_rhs = self.pixel_rhs[:, chosen, :]
        return subset

    @property
    def matrix(self) -> np.ndarray:
        """(6, npix) view, MATRIX_ENTRIES order."""
        return self.pixel_matrix.T

    @property
    def rhs(self) -> np.ndarray:
        """(n_tods, 3, npix) view."""
        return np.moveaxis(self.pixel_rhs, 0, 2)

    def add(
        self,
        pixels,
        cos_2alpha,
        sin_2alpha,
        weights,
        pol_efficiency,
        tods,
        tod_detectors=None,
        rows=None,
    ) -> None:
        """Add samples: pixels, angles (n_det, n); weights, pol_efficiency (n_det,);
        tods: a sequence of n_tods arrays (n_det, n), or with ``rows`` an array
        (n_rows, n_det, n) of which TOD i is row ``rows[i]`` (no copy: a row may be binned
        for several TODs). ``tod_detectors[i]``, if given and not None, is the only
        detector whose samples TOD i has (the others are zero)."""
        if rows is None:
            rows = np.arange(len(tods))
            stacked = np.empty((len(tods), *np.shape(pixels)))
            for index, tod in enumerate(tods):
                stacked[index] = tod
            tods = stacked
        rows = np.asarray(rows, dtype=np.int64)
        if rows.size != self.n_tods:
            raise ValueError(f"expected {self.n_tods} TODs, got {rows.size}")
        if tod_detectors is None:
            tod_detectors = [None] * self.n_tods
        owners = np.array([-1 if k is None else int(k) for k in tod_detectors], dtype=np.int64)
        _add_samples(
            pixels,
            cos_2alpha,
            sin_2alpha,
            np.ascontiguousarray(weights, dtype=np.float64),
            np.ascontiguousarray(pol_efficiency, dtype=np.float64),
            tods,
            rows,
            owners,
            self.pixel_matrix,
            self.pixel_rhs,
            self.hits,
        )

    def full_matrix(self) -> np.ndarray:
        """(npix, 3, 3) symmetric matrices."""
        return symmetric_matrices(self.pixel_matrix)

    def reorder(self, source: np.ndarray) -> None:
        """Pixel p takes the numbers of pixel ``source[p]`` (a change of ordering)."""
        self.pixel_matrix = self.pixel_matrix[source]
        self.pixel_rhs = self.pixel_rhs[source]
        self.hits = self.hits[source]

    def merge(self, other: NormalEquations) -> None:
        """Add another accumulation (e.g. from another process or time range)."""
        self.pixel_matrix += other.pixel_matrix
        self.pixel_rhs += other.pixel_rhs
        self.hits += other.hits


def condition_numbers(matrices: np.ndarray) -> np.ndarray:
    """cond = lambda_max / lambda_min of each symmetric 3x3 matrix (inf if singular)."""
    eigenvalues = np.linalg.eigvalsh(matrices)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = eigenvalues[:, -1] / eigenvalues[:, 0]
    cond[~(eigenvalues[:, 0] > 0)] = np.inf
    return cond


def solve_maps(equations: NormalEquations, max_condition_number: float):
    """Binned I, Q, U maps for each accumulated TOD; ill-conditioned pixels = UNSEEN.

    Returns (maps (n_tods, 3, npix), condition (npix,), good (npix,) bool).
    """
    matrices = equations.full_matrix()
    cond = condition_numbers(matrices)
    good = (equations.hits > 0) & (cond < max_condition_number)
    maps = np.full((equations.n_tods, 3, equations.npix), hp.UNSEEN)
    if good.any():
        rhs = np.moveaxis(equations.rhs[:, :, good], 2, 0)  # (n_good, n_tods, 3)
        solution = np.linalg.solve(matrices[good], np.swapaxes(rhs, 1, 2))  # (n_good, 3, n_tods)
        maps[:, :, good] = np.moveaxis(solution, 0, 2).swapaxes(0, 1)
    return maps, cond, good


@numba.njit(cache=True, nogil=True)
def _add_samples(
    pixels, cos_2alpha, sin_2alpha, weights, rho, tods, rows, owners, matrix, rhs, hits
):
    """matrix[p] += w [1, a1, a2, a1 a1, a1 a2, a2 a2] and rhs[p, i] += w d_i [1, a1, a2]
    for every TOD i, d_i = tods[rows[i]] (the detectors' samples only where ``owners[i]``
    is -1 or the detector), a = rho (cos, sin) 2 alpha; one pass over the samples,
    detector by detector in time order (MATRIX_ENTRIES order)."""
    for det in range(pixels.shape[0]):
        w = weights[det]
        for t in range(pixels.shape[1]):
            p = pixels[det, t]
            a1 = rho[det] * cos_2alpha[det, t]
            a2 = rho[det] * sin_2alpha[det, t]
            hits[p] += 1
            matrix[p, 0] += w
            matrix[p, 1] += w * a1
            matrix[p, 2] += w * a2
            matrix[p, 3] += w * a1 * a1
            matrix[p, 4] += w * a1 * a2
            matrix[p, 5] += w * a2 * a2
            for i in range(rows.shape[0]):
                if owners[i] >= 0 and owners[i] != det:
                    continue
                x = w * tods[rows[i], det, t]
                rhs[p, i, 0] += x
                rhs[p, i, 1] += x * rho[det] * cos_2alpha[det, t]
                rhs[p, i, 2] += x * rho[det] * sin_2alpha[det, t]


# the weights y_t of the per-detector moment matrices sum_t w_k y_t a^T a (PixelMoments)
MOMENT_WEIGHTS = ("1", "h", "h*h")


class PixelMoments:
    """Per detector k and pixel p, the 3 x 3 matrices sum_{t in k, p} w_k y_t a_t^T a_t for
    y = 1, h, h^2 (h: the unit HWPSS of detector k), in MATRIX_ENTRIES order.

    With white noise n of variance sigma_k^2 = 1 / w_k, the binned vectors
    b_k = sum w_k a^T n and c_k = sum w_k a^T h n are jointly Gaussian with covariance
    [[M_k, H_k], [H_k, Q_k]] (M, H, Q = the y = 1, h, h^2 moments), and the binned map of
    h times a pixelized sky m is M^-1 sum_k H_k m: the seed-dependent part of the s h
    template term in the map domain (:mod:`map_domain`). Stored per pixel, contiguous
    (one cache line per sample), as ``values`` (n_det, npix, 3 weights, 6 entries)."""

    def __init__(self, nside: int, n_det: int):
        self.nside = nside
        self.npix = hp.nside2npix(nside)
        self.values = np.zeros((n_det, self.npix, len(MOMENT_WEIGHTS), 6))

    def reorder(self, source: np.ndarray) -> None:
        """Pixel p takes the numbers of pixel ``source[p]`` (a change of ordering)."""
        self.values = self.values[:, source]

    def add(self, pixels, cos_2alpha, sin_2alpha, weights, pol_efficiency, hwpss) -> None:
        """Add samples: pixels, angles, hwpss (n_det, n); weights, pol_efficiency (n_det,)."""
        _add_moments(
            pixels,
            cos_2alpha,
            sin_2alpha,
            np.ascontiguousarray(weights, dtype=np.float64),
            np.ascontiguousarray(pol_efficiency, dtype=np.float64),
            hwpss,
            self.values,
        )


def symmetric_matrices(entries: np.ndarray) -> np.ndarray:
    """(..., 3, 3) symmetric matrices from their 6 entries (..., 6) in MATRIX_ENTRIES order."""
    full = np.empty((*entries.shape[:-1], 3, 3))
    for entry, (i, j) in enumerate(MATRIX_ENTRIES):
        full[..., i, j] = full[..., j, i] = entries[..., entry]
    return full


@numba.njit(cache=True, nogil=True)
def _add_moments(pixels, cos_2alpha, sin_2alpha, weights, rho, hwpss, moments):
    """moments[k, p, j, :] += w_k h^j [1, a1, a2, a1 a1, a1 a2, a2 a2], j = 0, 1, 2."""
    for det in range(pixels.shape[0]):
        w = weights[det]
        for t in range(pixels.shape[1]):
            p = pixels[det, t]
            a1 = rho[det] * cos_2alpha[det, t]
            a2 = rho[det] * sin_2alpha[det, t]
            h = hwpss[det, t]
            y = w
            for j in range(3):
                moments[det, p, j, 0] += y
                moments[det, p, j, 1] += y * a1
                moments[det, p, j, 2] += y * a2
                moments[det, p, j, 3] += y * a1 * a1
                moments[det, p, j, 4] += y * a1 * a2
                moments[det, p, j, 5] += y * a2 * a2
                y *= h
