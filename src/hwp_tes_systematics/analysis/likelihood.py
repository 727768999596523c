"""Likelihood of the tensor-to-scalar ratio r from the BB spectrum of the CMB residual.

The study (Micheli et al. 2024, eq. 10, after Hamimeche & Lewis 2008) fits r to

    C_obs(ell)   = C_res(ell) + C_lens(ell)
    C_mod(ell|r) = r C_GW^{r=1}(ell) + C_lens(ell) + C_FGres(ell) + N(ell)

    -2 ln L(r) = sum_{ell=lmin}^{lmax} (2 ell + 1) f_sky
                 [ ln C_mod + C_obs / C_mod - (2 ell - 1) / (2 ell + 1) ln C_obs ]      (1)

where C_res is the BB spectrum of (recovered - input) CMB maps after component
separation (noise + foreground residual + systematics), C_lens the lensing BB, C_GW^{r=1}
the primordial tensor BB for r = 1 (both from the PTEP spectra, :mod:`sky`), C_FGres the
expected foreground residual and N the noise spectrum after component separation. All
C_ell are C_ell (not D_ell) in K_CMB^2; r is dimensionless.

Properties of (1), used below:

* it is, up to f_sky, minus twice the log of the exact full-sky distribution of one
  measured C_obs with nu = 2 ell + 1 modes (a scaled chi^2_nu, i.e. a Wishart of
  dimension 1): p(C_obs | C_mod) ~ C_obs^{(nu - 2)/2} C_mod^{-nu/2} exp(-nu C_obs / (2 C_mod));
  f_sky scales the number of modes;
* the last term, -(2 ell - 1) ln C_obs, does not depend on r: it only shifts -2 ln L by a
  constant and has no effect on the normalised likelihood, its maximum or its quantiles;
* for each ell the bracket is minimal at C_mod = C_obs, whatever the last term, so if
  C_obs = C_mod(r_in) at every ell the maximum-likelihood r is exactly r_in. Writing
  x = C_obs / C_mod, (1) equals

      -2 ln L(r) = sum (2 ell + 1) f_sky [x - 1 - ln x]  +  sum f_sky [2 ln C_obs + 2 ell + 1]

  The first sum (the "deviance", >= 0, zero at C_mod = C_obs) is what is computed: it
  avoids the cancellation of terms ln C ~ -40 summed over hundreds of multipoles; the
  second, r-independent, sum is added back by :func:`minus_two_log_likelihood`;
* near its minimum (C_obs = C_mod(r0)), d^2(-2 ln L)/dr^2 = sum (2 ell + 1) f_sky (C_GW/C_mod)^2,
  so -2 ln L ~ (r - r0)^2 / sigma_r^2 with the Fisher width

      sigma_r(r0) = [ sum (2 ell + 1) f_sky / 2 (C_GW^{r=1} / C_mod(r0))^2 ]^{-1/2}.      (2)

Bias from an added spectrum (:func:`fisher_bias`): to first order in a systematic
spectrum C_sys added to C_obs, the maximum of (1) moves by

    delta r = sum w_ell C_GW C_sys / C_mod(r0)^2 / sum w_ell (C_GW / C_mod(r0))^2,
    w_ell = (2 ell + 1) f_sky / 2,                                                   (3)

linear in C_sys (the bias formula of LiteBIRD's systematics studies, PTEP 2023). It is
signed, and exactly quadratic in sigma_g1 when C_sys is the spectrum of a systematic
that scales as sigma_g1.

The prior is r >= 0: grids start at 0. The paper's estimator is the "68 % point": the r
where the cumulative integral of the normalised L(r) from 0 reaches 0.68 (an upper bound
when L peaks at r = 0: for a half-Gaussian of width sigma it is 0.9945 sigma).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.special import erfinv

from .. import sky

log = logging.getLogger(__name__)

DEFAULT_FRACTION = 0.68  # the paper's "68 %-L" point
DEFAULT_N_GRID = 20001  # points of the r grid
# Tail criterion of the adaptive grid: -2 ln L at r_max must exceed its minimum by this
# (30 = 5.5 sigma for a Gaussian: the mass beyond r_max is < 1e-7 of the total).
DEFAULT_TAIL_DELTA_CHI2 = 30.0
# The grid must resolve the likelihood: at least this many grid steps per Fisher width
# at the peak. The 68 % point from the trapezoid CDF, linearly interpolated, is then
# within ~3e-6 sigma (1e-7 sigma at 1000 steps; measured on Gaussians); the error is
# smooth in C_obs, so it cancels in r_sys - r_nosys computed on one grid.
MIN_STEPS_PER_SIGMA = 200
_CHUNK_ELEMENTS = 2_000_000  # r x ell values per chunk of deviance()
ARCMIN_TO_RAD = np.pi / (180.0 * 60.0)
UK_TO_K = 1e-6


def half_normal_quantile(fraction: float) -> float:
    """x / sigma such that a half-normal distribution has CDF ``fraction`` at x.

    CDF(x) = erf(x / (sqrt(2) sigma)), so x = sqrt(2) erfinv(fraction) sigma
    (0.9945 sigma for fraction = 0.68).
    """
    return float(np.sqrt(2.0) * erfinv(fraction))


def white_noise_bb(ell, depth_uk_arcmin: float, fwhm_arcmin: float) -> np.ndarray:
    """Beam-deconvolved white-noise spectrum N_ell [K_CMB^2] of a map of depth ``depth``.

    N_ell = (depth [uK arcmin] x 1e-6 x pi / (180 x 60))^2 / B_ell^2, with the Gaussian
    beam B_ell = exp(-ell (ell + 1) sigma_b^2 / 2), sigma_b = FWHM / sqrt(8 ln 2) [rad].
    ``depth`` is the polarisation (Q, U) noise level; ``fwhm_arcmin = 0``: no beam.
    """
    ell = np.asarray(ell, dtype=float)
    if not np.isfinite(depth_uk_arcmin) or depth_uk_arcmin < 0:
        raise ValueError(f"depth_uk_arcmin = {depth_uk_arcmin}: expected a noise level >= 0")
    if not np.isfinite(fwhm_arcmin) or fwhm_arcmin < 0:
        raise ValueError(f"fwhm_arcmin = {fwhm_arcmin}: expected a beam FWHM >= 0")
    sigma_b = fwhm_arcmin * ARCMIN_TO_RAD / np.sqrt(8.0 * np.log(2.0))
    white = (depth_uk_arcmin * UK_TO_K * ARCMIN_TO_RAD) ** 2
    return white * np.exp(ell * (ell + 1.0) * sigma_b**2)


def _as_spectrum(name: str, values, size: int) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim == 0:
        array = np.full(size, float(array))
    if array.shape != (size,):
        raise ValueError(f"{name}: expected shape ({size},) like ell, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: non-finite values")
    return array


@dataclass(frozen=True, eq=False)
class BBModel:
    """The BB model of eq. (1): C_mod(ell | r) = r C_GW^{r=1} + C_lens + C_FGres + N.

    Attributes: ``ell`` (integer multipoles, 1-D) and, on the same ell, the spectra
    ``c_lens``, ``c_gw_r1``, ``c_fg_res``, ``n_ell`` [K_CMB^2] (C_ell, not D_ell;
    scalars are broadcast); ``f_sky`` in (0, 1]; the likelihood sums over
    ``lmin <= ell <= lmax`` (``lmin >= 2``; ``lmax = None``: the largest ell).
    The spectra of an observation (``c_obs``) must be given on the same ``ell``.
    """

    ell: np.ndarray
    c_lens: np.ndarray
    c_gw_r1: np.ndarray
    c_fg_res: np.ndarray
    n_ell: np.ndarray
    f_sky: float
    lmin: int = 2
    lmax: int | None = None
    mask: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        ell = np.asarray(self.ell)
        if ell.ndim != 1 or ell.size == 0:
            raise ValueError(f"ell: expected a non-empty 1-D array, got shape {ell.shape}")
        if not np.all(np.isfinite(ell)) or np.any(ell != np.round(ell)):
            raise ValueError("ell: expected integer multipoles")
        ell = np.round(ell).astype(int)
        set_ = object.__setattr__
        set_(self, "ell", ell)
        for name in ("c_lens", "c_gw_r1", "c_fg_res", "n_ell"):
            set_(self, name, _as_spectrum(name, getattr(self, name), ell.size))
        f_sky = float(self.f_sky)
        if not 0.0 < f_sky <= 1.0:
            raise ValueError(f"f_sky = {self.f_sky}: expected 0 < f_sky <= 1")
        set_(self, "f_sky", f_sky)
        lmax = int(ell.max()) if self.lmax is None else int(self.lmax)
        lmin = int(self.lmin)
        if lmin < 2 or lmax < lmin:
            raise ValueError(f"lmin = {lmin}, lmax = {lmax}: expected 2 <= lmin <= lmax")
        mask = (ell >= lmin) & (ell <= lmax)
        if np.count_nonzero(mask) != lmax - lmin + 1:
            raise ValueError(f"ell does not hold every multipole of [{lmin}, {lmax}] once")
        set_(self, "lmin", lmin)
        set_(self, "lmax", lmax)
        set_(self, "mask", mask)
        if np.any(self.c_gw_r1[mask] < 0) or np.any(self.c_fg_res[mask] < 0):
            raise ValueError("c_gw_r1 and c_fg_res must be >= 0")
        if np.any(self.c_mod(0.0)[mask] <= 0):
            raise ValueError(
                "C_mod(r = 0) = C_lens + C_FGres + N must be > 0 for lmin <= ell <= lmax"
            )

    @classmethod
    def from_ptep(
        cls, f_sky: float, lmin: int = 2, lmax: int = 200, n_ell=0.0, c_fg_res=0.0
    ) -> BBModel:
        """Model on ell = 0..lmax with the PTEP lensing and r = 1 tensor BB of :mod:`sky`.

        ``n_ell`` and ``c_fg_res`` [K_CMB^2]: scalars or arrays on ell = 0..lmax.
        """
        ell = np.arange(int(lmax) + 1)
        return cls(
            ell=ell,
            c_lens=sky.lensing_bb(lmax),
            c_gw_r1=sky.tensor_bb_r1(lmax),
            c_fg_res=c_fg_res,
            n_ell=n_ell,
            f_sky=f_sky,
            lmin=lmin,
            lmax=lmax,
        )

    @property
    def ell_used(self) -> np.ndarray:
        """The multipoles lmin..lmax of the sum."""
        return self.ell[self.mask]

    def c_mod(self, r) -> np.ndarray:
        """C_mod(ell | r) = r C_GW^{r=1} + C_lens + C_FGres + N [K_CMB^2] on ``ell``.

        Scalar r: shape (n_ell,); array r: shape r.shape + (n_ell,).
        """
        r = np.asarray(r, dtype=float)[..., None]
        return r * self.c_gw_r1 + (self.c_lens + self.c_fg_res + self.n_ell)

    def c_obs_from_residual(self, c_res) -> np.ndarray:
        """C_obs = C_res + C_lens [K_CMB^2] (the paper's observed spectrum)."""
        return _as_spectrum("c_res", c_res, self.ell.size) + self.c_lens

    def with_transfer(self, transfer, tensor_transfer=None) -> BBModel:
        """The model of a CMB seen through a filter: C_lens times ``transfer``, C_GW times
        ``tensor_transfer`` (default ``transfer``), both on ``ell``; the rest unchanged."""
        transfer = _as_spectrum("transfer", transfer, self.ell.size)
        tensor = transfer if tensor_transfer is None else tensor_transfer
        tensor = _as_spectrum("tensor_transfer", tensor, self.ell.size)
        return BBModel(
            ell=self.ell,
            c_lens=self.c_lens * transfer,
            c_gw_r1=self.c_gw_r1 * tensor,
            c_fg_res=self.c_fg_res,
            n_ell=self.n_ell,
            f_sky=self.f_sky,
            lmin=self.lmin,
            lmax=self.lmax,
        )

    def fisher_terms(self, r: float = 0.0) -> np.ndarray:
        """F_ell = (2l+1) f_sky / 2 (C_GW / C_mod(r))^2 for lmin <= ell <= lmax."""
        ratio = self.c_gw_r1[self.mask] / self.c_mod(r)[self.mask]
        return (2 * self.ell_used + 1) * self.f_sky / 2.0 * ratio**2

    def fisher_sigma_r(self, r: float = 0.0) -> float:
        """Fisher width of eq. (2): [sum (2l+1) f_sky / 2 (C_GW / C_mod(r))^2]^(-1/2)."""
        fisher = np.sum(self.fisher_terms(r))
        if fisher <= 0:
            raise ValueError("no tensor signal in the multipole range: sigma_r is infinite")
        return float(fisher**-0.5)


def linear_r_estimate(c_obs, model: BBModel, r_fiducial: float = 0.0) -> float:
    """r from one observed spectrum by one Newton step of eq. (1) from ``r_fiducial``:

        r_hat = r_f + sum w g (C_obs - C_mod(r_f)) / C_mod(r_f)^2 / sum w (g / C_mod(r_f))^2,

    w = (2 ell + 1) f_sky / 2, g = the model's C_GW^{r=1} (with its transfer). Linear in
    C_obs and free of the prior r >= 0, so its mean over realizations is the true r
    whenever the model's C_mod(r) is the mean of C_obs, whatever r_f (which only sets
    the weights); its scatter is then the Fisher width sigma_r(r_f) of eq. (2)."""
    c_obs = _as_spectrum("c_obs", c_obs, model.ell.size)[model.mask]
    c_mod = model.c_mod(r_fiducial)[model.mask]
    weight = (2 * model.ell_used + 1) * model.f_sky / 2.0 * model.c_gw_r1[model.mask] / c_mod**2
    return float(
        r_fiducial + np.sum(weight * (c_obs - c_mod)) / np.sum(model.fisher_terms(r_fiducial))
    )


def fisher_bias(c_sys, model: BBModel, r: float = 0.0) -> float:
    """delta r of eq. (3): the first-order shift of the maximum of L when ``c_sys``
    [K_CMB^2] (on ``model.ell``) is added to C_obs = C_mod(r); signed, linear in c_sys."""
    return float(np.sum(_bias_terms(c_sys, model, r)) / np.sum(model.fisher_terms(r)))


def _bias_terms(c_sys, model: BBModel, r: float) -> np.ndarray:
    """The numerator terms of eq. (3), (2l+1) f_sky / 2 C_GW C_sys / C_mod(r)^2, for
    lmin <= ell <= lmax (``c_sys`` [K_CMB^2] on ``model.ell``)."""
    c_sys = _as_spectrum("c_sys", c_sys, model.ell.size)[model.mask]
    weight = (2 * model.ell_used + 1) * model.f_sky / 2.0
    return weight * model.c_gw_r1[model.mask] * c_sys / model.c_mod(r)[model.mask] ** 2


def _checked_c_obs(c_obs, model: BBModel) -> np.ndarray:
    c_obs = _as_spectrum("c_obs", c_obs, model.ell.size)
    if np.any(c_obs[model.mask] <= 0):
        raise ValueError(f"c_obs must be > 0 for {model.lmin} <= ell <= {model.lmax}")
    return c_obs


def _checked_r(r_grid) -> np.ndarray:
    r_grid = np.asarray(r_grid, dtype=float)
    if r_grid.ndim != 1 or r_grid.size < 2:
        raise ValueError(f"r_grid: expected a 1-D grid of >= 2 values, got shape {r_grid.shape}")
    if not np.all(np.isfinite(r_grid)) or np.any(np.diff(r_grid) <= 0):
        raise ValueError("r_grid: expected finite, strictly increasing values")
    return r_grid


def deviance(r_grid, c_obs, model: BBModel) -> np.ndarray:
    """-2 ln L(r) minus its r-independent part: sum (2l+1) f_sky [x - 1 - ln x], x = C_obs/C_mod(r).

    >= 0, zero where C_mod = C_obs at every ell; vectorised over ``r_grid`` (any shape,
    evaluated in chunks of r to bound the memory). Same shape as ``r_grid``.
    """
    r = np.asarray(r_grid, dtype=float)
    c_obs = _checked_c_obs(c_obs, model)[model.mask]
    weight = (2 * model.ell_used + 1) * model.f_sky
    c_gw = model.c_gw_r1[model.mask]
    c_fixed = (model.c_lens + model.c_fg_res + model.n_ell)[model.mask]
    flat = r.ravel()
    out = np.empty(flat.size)
    chunk = max(1, _CHUNK_ELEMENTS // c_obs.size)
    for start in range(0, flat.size, chunk):
        c_mod = flat[start : start + chunk, None] * c_gw + c_fixed
        if np.any(c_mod <= 0):
            raise ValueError("C_mod(r) <= 0 at some ell: r out of the model's domain")
        x = c_obs / c_mod
        out[start : start + chunk] = (x - 1.0 - np.log(x)) @ weight
    return out.reshape(r.shape)


def minus_two_log_likelihood(r_grid, c_obs, model: BBModel) -> np.ndarray:
    """-2 ln L(r) of eq. (1), vectorised over ``r_grid`` (dimensionless), C_obs in K_CMB^2.

    Computed as :func:`deviance` + sum f_sky [2 ln C_obs + 2 ell + 1] (exactly eq. 1).
    """
    c_obs = _checked_c_obs(c_obs, model)
    ell = model.ell_used
    constant = np.sum(model.f_sky * (2.0 * np.log(c_obs[model.mask]) + 2 * ell + 1))
    return deviance(r_grid, c_obs, model) + constant


def r_grid(r_max: float, n: int = DEFAULT_N_GRID) -> np.ndarray:
    """Uniform grid of ``n`` values of r from 0 (the r >= 0 prior) to ``r_max``."""
    r_max = float(r_max)
    if not np.isfinite(r_max) or r_max <= 0:
        raise ValueError(f"r_max = {r_max}: expected > 0")
    if int(n) < 3:
        raise ValueError(f"n = {n}: expected >= 3 grid points")
    return np.linspace(0.0, r_max, int(n))


def _curve_from_deviance(r_grid, dev) -> np.ndarray:
    like = np.exp(-0.5 * (dev - np.min(dev)))
    norm = np.trapezoid(like, r_grid)
    return like / norm


def likelihood_curve(
    r_grid, c_obs, model: BBModel, tail_delta_chi2: float | None = DEFAULT_TAIL_DELTA_CHI2
) -> np.ndarray:
    """Normalised likelihood L(r) = exp(-(chi2(r) - min chi2) / 2) / integral, on ``r_grid``.

    chi2 = -2 ln L of eq. (1); the integral over the grid is 1 (trapezoid rule), so L is a
    density in 1/r. ValueError if the grid truncates the likelihood: chi2 at the last grid
    point less than ``tail_delta_chi2`` above the minimum (None: no check); use
    :func:`adaptive_r_grid` for a grid that holds the whole likelihood.
    """
    r_grid = _checked_r(r_grid)
    dev = deviance(r_grid, c_obs, model)
    if tail_delta_chi2 is not None and dev[-1] - dev.min() < tail_delta_chi2:
        raise ValueError(
            f"r grid up to {r_grid[-1]:.4g} truncates the likelihood: -2 ln L rises by only "
            f"{dev[-1] - dev.min():.3g} < {tail_delta_chi2} at r_max; extend r_max "
            "(adaptive_r_grid)"
        )
    return _curve_from_deviance(r_grid, dev)


def cumulative(r_grid, likelihood) -> np.ndarray:
    """CDF(r) = integral_0^r L dr' / integral over the grid (cumulative trapezoid), CDF[0] = 0."""
    r_grid = _checked_r(r_grid)
    likelihood = np.asarray(likelihood, dtype=float)
    if likelihood.shape != r_grid.shape or np.any(likelihood < 0):
        raise ValueError("likelihood: expected non-negative values on r_grid")
    steps = 0.5 * (likelihood[1:] + likelihood[:-1]) * np.diff(r_grid)
    cdf = np.concatenate([[0.0], np.cumsum(steps)])
    if cdf[-1] <= 0:
        raise ValueError("likelihood: zero integral over the grid")
    return cdf / cdf[-1]


def r_at_fraction(r_grid, likelihood, fraction: float = DEFAULT_FRACTION) -> float:
    """The r where the CDF of L from r = 0 reaches ``fraction`` (the paper's 68 % point).

    The CDF is the cumulative trapezoid integral (:func:`cumulative`), linearly
    interpolated. With the r >= 0 prior this is an upper bound when L peaks at r = 0.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction = {fraction}: expected 0 < fraction < 1")
    r_grid = _checked_r(r_grid)
    cdf = cumulative(r_grid, likelihood)
    # first index where cdf >= fraction; cdf is non-decreasing (flat where L = 0)
    index = int(np.searchsorted(cdf, fraction, side="left"))
    low, high = cdf[index - 1], cdf[index]
    return float(
        r_grid[index - 1] + (fraction - low) / (high - low) * (r_grid[index] - r_grid[index - 1])
    )


def r_maximum_likelihood(r_grid, likelihood) -> float:
    """r of the maximum of L on the grid, refined by a parabola through ln L at the three
    points around the grid maximum (exact for a Gaussian); the grid value at an edge."""
    r_grid = _checked_r(r_grid)
    likelihood = np.asarray(likelihood, dtype=float)
    index = int(np.argmax(likelihood))
    if index == 0 or index == r_grid.size - 1 or np.any(likelihood[index - 1 : index + 2] <= 0):
        return float(r_grid[index])
    y0, y1, y2 = np.log(likelihood[index - 1 : index + 2])
    x0, x1, x2 = r_grid[index - 1 : index + 2]
    # vertex of the parabola through (x0, y0), (x1, y1), (x2, y2)
    numerator = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
    denominator = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
    if denominator == 0:
        return float(x1)
    return float(np.clip(x1 - 0.5 * numerator / denominator, x0, x2))


def adaptive_r_grid(
    c_obs,
    model: BBModel,
    n: int = DEFAULT_N_GRID,
    tail_delta_chi2: float = DEFAULT_TAIL_DELTA_CHI2,
    n_sigma_start: float = 6.0,
    max_doublings: int = 40,
    max_n: int = 2_000_001,
) -> np.ndarray:
    """A grid 0..r_max of at least ``n`` points that holds the whole likelihood.

    ``c_obs``: one spectrum (n_ell,) or several (k, n_ell) [K_CMB^2] on ``model.ell``;
    with several, the grid suits all of them: use one grid for the spectra whose r are
    compared (with and without systematics), so that the discretisation errors of
    :func:`r_at_fraction` (O(step^2), smooth in C_obs) cancel in their difference.

    r_max starts at ``n_sigma_start`` x sigma_r(0) (Fisher width, eq. 2) and doubles
    until -2 ln L at r_max exceeds its minimum on the grid by ``tail_delta_chi2`` for
    every spectrum (the neglected tail is then < ~1e-7 of the total for the default 30).
    The number of points is then raised, if needed, to give at least
    ``MIN_STEPS_PER_SIGMA`` steps per Fisher width at each peak. ValueError after
    ``max_doublings`` doublings or if more than ``max_n`` points would be needed.
    """
    c_obs = np.asarray(c_obs, dtype=float)
    spectra = [_checked_c_obs(c, model) for c in np.atleast_2d(c_obs)]
    n = int(n)
    r_max = n_sigma_start * model.fisher_sigma_r(0.0)
    for _ in range(max_doublings + 1):
        grid = r_grid(r_max, n)
        devs = [deviance(grid, c, model) for c in spectra]
        if all(dev[-1] - dev.min() >= tail_delta_chi2 for dev in devs):
            break
        r_max *= 2.0
    else:
        raise ValueError(
            f"adaptive_r_grid: the likelihood is not negligible at r_max = {r_max / 2:.3g} "
            f"after {max_doublings} doublings"
        )
    sigma_peak = min(model.fisher_sigma_r(float(grid[np.argmin(dev)])) for dev in devs)
    n_needed = int(np.ceil(MIN_STEPS_PER_SIGMA * r_max / sigma_peak)) + 1
    if n_needed > n:
        if n_needed > max_n:
            raise ValueError(
                f"adaptive_r_grid: {n_needed} points would be needed up to r_max = "
                f"{r_max:.3g} for {MIN_STEPS_PER_SIGMA} steps per Fisher width "
                f"{sigma_peak:.3g} (max_n = {max_n})"
            )
        log.debug("adaptive_r_grid: %d -> %d points to resolve the peak", n, n_needed)
        grid = r_grid(r_max, n_needed)
    return grid


@dataclass(frozen=True)
class RResult:
    """Result of :func:`fit_r`: the grid, L(r) on it, the ``fraction`` point, the maximum
    of L, and the Fisher width at r = 0 and at the maximum."""

    r_grid: np.ndarray = field(repr=False)
    likelihood: np.ndarray = field(repr=False)
    fraction: float
    r_fraction: float
    r_ml: float
    sigma_r_fisher_0: float
    sigma_r_fisher_ml: float


def fit_r(
    c_res,
    model: BBModel,
    fraction: float = DEFAULT_FRACTION,
    n: int = DEFAULT_N_GRID,
    grid=None,
) -> RResult:
    """The paper's r estimate from a residual BB spectrum ``c_res`` [K_CMB^2] on ``model.ell``.

    C_obs = C_res + C_lens; grid ``grid`` (default :func:`adaptive_r_grid` with ``n``
    points), normalised L(r) (:func:`likelihood_curve`, which checks the grid holds the
    likelihood), the ``fraction`` point (:func:`r_at_fraction`) and the maximum
    (:func:`r_maximum_likelihood`).
    """
    c_obs = model.c_obs_from_residual(c_res)
    grid = adaptive_r_grid(c_obs, model, n=n) if grid is None else _checked_r(grid)
    like = likelihood_curve(grid, c_obs, model)
    r_ml = r_maximum_likelihood(grid, like)
    return RResult(
        r_grid=grid,
        likelihood=like,
        fraction=float(fraction),
        r_fraction=r_at_fraction(grid, like, fraction),
        r_ml=r_ml,
        sigma_r_fisher_0=model.fisher_sigma_r(0.0),
        sigma_r_fisher_ml=model.fisher_sigma_r(r_ml),
    )


def fit_r_common_grid(
    c_res_list, model: BBModel, fraction: float = DEFAULT_FRACTION, n: int = DEFAULT_N_GRID
) -> list[RResult]:
    """:func:`fit_r` of several residual spectra on one adaptive grid (e.g. with and
    without systematics for one seed), so that grid errors cancel in r_sys - r_nosys."""
    c_obs = np.array([model.c_obs_from_residual(c) for c in c_res_list])
    grid = adaptive_r_grid(c_obs, model, n=n)
    return [fit_r(c, model, fraction=fraction, grid=grid) for c in c_res_list]


# ================================================= where the information and bias come from
def fisher_information_per_ell(model: BBModel, r: float = 0.0) -> np.ndarray:
    """F_ell (:meth:`BBModel.fisher_terms`) on ``model.ell``, 0 outside lmin..lmax:
    sum F_ell = 1 / sigma_r^2 (eq. 2)."""
    out = np.zeros(model.ell.size)
    out[model.mask] = model.fisher_terms(r)
    return out


def fisher_bias_per_ell(c_sys, model: BBModel, r: float = 0.0) -> np.ndarray:
    """The terms of eq. (3) per ell over sum F_ell (their sum is :func:`fisher_bias`), on
    ``model.ell``, 0 outside lmin..lmax."""
    out = np.zeros(model.ell.size)
    out[model.mask] = _bias_terms(c_sys, model, r) / np.sum(model.fisher_terms(r))
    return out


# ============================================== delta r of the systematic's own power, 68 %
def fraction_point_shift(
    c_res_nosys,
    c_sys_unit,
    model: BBModel,
    sigmas,
    fraction: float = DEFAULT_FRACTION,
    stop_above: float | None = None,
) -> np.ndarray:
    """The paper's delta r for the systematic's own power: the shift of the ``fraction``
    point of L(r) when sigma^2 C_sys is added to the no-systematics residual,

        delta r(sigma) = r_f(C_res + sigma^2 C_sys) - r_f(C_res),

    for each sigma of ``sigmas`` [1/K], ascending (``c_sys_unit`` in K^2 K^2 per unit
    sigma^2); each pair on one grid (:func:`fit_r_common_grid`), so the grid's error
    cancels in the difference. Found numerically through eq. (1): the quadratic law at
    small sigma is a check, not an assumption. ``stop_above``: once a shift exceeds it,
    the larger sigmas are not computed (NaN): far beyond the budget the likelihood would
    need ever finer and wider grids for nothing. A sigma whose pair no grid of
    :func:`adaptive_r_grid` can hold (a shift of many thousand Fisher widths: the paper's
    model without the notch's transfer, where sigma_r is ~1e-4) ends the scan the same
    way, with a warning."""
    sigmas = np.asarray(sigmas, dtype=float)
    if np.any(np.diff(sigmas) <= 0):
        raise ValueError("sigmas: expected ascending values")
    c_res_nosys = _as_spectrum("c_res_nosys", c_res_nosys, model.ell.size)
    c_sys_unit = _as_spectrum("c_sys_unit", c_sys_unit, model.ell.size)
    shifts = np.full(sigmas.size, np.nan)
    for index, sigma in enumerate(sigmas):
        try:
            nosys, contaminated = fit_r_common_grid(
                [c_res_nosys, c_res_nosys + sigma**2 * c_sys_unit], model, fraction=fraction
            )
        except ValueError as error:
            log.warning("fraction_point_shift: stopped at sigma = %.3g (NaN on): %s", sigma, error)
            break
        shifts[index] = contaminated.r_fraction - nosys.r_fraction
        if stop_above is not None and shifts[index] > stop_above:
            break
    return shifts
