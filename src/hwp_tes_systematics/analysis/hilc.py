"""Harmonic internal linear combination (HILC) of the frequency maps into a CMB estimate.

Method (Tegmark, de Oliveira-Costa & Hamilton 2003, PRD 68, 123523; the recipe of
FGBuster's ``harmonic_ilc``, re-implemented here because FGBuster cannot be installed):

1. every channel map (3, npix) I Q U [K_CMB], smoothed by its own Gaussian beam, is
   multiplied by a (possibly apodised) mask and transformed to T, E, B a_lm
   (:func:`maps_to_alm`);
2. the a_lm are brought to a common Gaussian beam (:func:`deconvolve_to_common_beam`),
   so that the sky signal is the same in every channel up to its frequency scaling;
3. separately for T, E and B and for each multipole bin b, the empirical channel
   covariance (:func:`empirical_covariance`)

       C_ij(b) = (1 / n_b) sum_{ell in b} [ Re(a_i,l0 a_j,l0^*) + 2 sum_{m=1}^{ell} Re(a_i,lm a_j,lm^*) ],
       n_b     = sum_{ell in b} (2 ell + 1)

   (both signs of m: for a real field a_l,-m = (-1)^m a_lm^*, so the m < 0 modes repeat
   the m > 0 ones; no mean is subtracted, a_lm have zero mean) gives the weights
   (:func:`ilc_weights`)

       w(b) = C(b)^-1 e / (e^T C(b)^-1 e),    e = (1, ..., 1),

   the linear combination with unit response to a signal with the CMB spectral energy
   distribution (all maps in K_CMB: the CMB is the same in every channel) and minimum
   variance: w minimises w^T C w under sum_i w_i = 1;
4. the CMB estimate is a^CMB_lm = sum_i w_i(b(ell)) a_i,lm (:func:`apply_weights`),
   zero for the ell outside every bin.

Because sum_i w_i = 1, the output is exactly CMB + sum_i w_i (foreground_i + noise_i):
the same weights applied to foreground-only or noise-only a_lm (:func:`apply_ilc`) give
the residual of each component. The empirical covariance includes the chance
correlation between the CMB and the foregrounds / noise in the finite number of modes of
a bin, so the minimum-variance weights slightly cancel part of the CMB against them (the
known "ILC bias", of relative order n_channels / n_b in power): bins must hold many more
modes than channels. With a mask the a_lm are those of the masked map; the number of
independent modes is then about f_sky n_b.

Numerics: the covariance is inverted as a correlation matrix (as in FGBuster),
C = D R D with D = diag(sqrt(C_ii)), so that channels of very different amplitude
(e.g. 40 and 402 GHz in K_CMB) do not spoil the conditioning. R is inverted by its
eigen-decomposition, discarding the eigenvalues below ``rcond`` (default
:data:`DEFAULT_RCOND`) times the largest one: for an invertible R this is the exact
inverse; for a singular one (e.g. noise-free inputs with fewer independent components
than channels) it is the pseudo-inverse, whose weights still satisfy sum w = 1 and give
the minimum variance (the discarded directions carry no variance). A bin with fewer
modes than channels has a rank-deficient covariance by construction; it raises
ValueError unless ``regularisation`` is "pinv" (pseudo-inverse as above) or a float
lambda > 0 (diagonal loading R + lambda I, i.e. C + lambda diag(C)).

Conventions: a_lm in healpy ordering (``hp.Alm.getidx``), m >= 0, complex; units K_CMB;
multipole bins are half-open integer ranges [l_start, l_stop) (:func:`multipole_bins`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import healpy as hp
import numpy as np

from ..sky import harmonics

log = logging.getLogger(__name__)

N_STOKES = 3  # T, E, B
STOKES_NAMES = ("T", "E", "B")
MIN_ELL_POL = 2  # E and B a_lm vanish at ell < 2 (spin-2 fields)
# Relative eigenvalue threshold of the correlation matrix (see the module docstring):
# eigenvalues < DEFAULT_RCOND x the largest are treated as zero. The eigenvalues of a
# numerically singular correlation matrix are ~1e-16 x n_channels, while the smallest
# physical ones (noise-to-signal power ratios) exceed ~1e-10 in this study.
DEFAULT_RCOND = 1e-12
MAP2ALM_ITER = 3  # Jacobi iterations of hp.map2alm (healpy's default for anafast)


# ============================================================================== bins
def _check_bins(bins, lmax: int | None = None) -> list[tuple[int, int]]:
    """Bins as a list of (l_start, l_stop) ints, increasing, non-overlapping, non-empty."""
    out = []
    for item in bins:
        try:
            start, stop = item
        except (TypeError, ValueError) as error:
            raise ValueError(f"bins: expected (l_start, l_stop) pairs, got {item!r}") from error
        if int(start) != start or int(stop) != stop:
            raise ValueError(f"bins: multipoles must be integers, got ({start}, {stop})")
        out.append((int(start), int(stop)))
    if not out:
        raise ValueError("bins: expected at least one multipole bin")
    previous_stop = 0
    for start, stop in out:
        if start < previous_stop or stop <= start:
            raise ValueError(
                f"bins {out}: expected non-empty, increasing, non-overlapping [l_start, l_stop) "
                "ranges with l_start >= 0"
            )
        previous_stop = stop
    if lmax is not None and out[-1][1] > int(lmax) + 1:
        raise ValueError(f"bins {out}: the last bin ends beyond lmax = {lmax}")
    return out


def multipole_bins(lmin: int, lmax: int, width: int) -> list[tuple[int, int]]:
    """Bins [l_start, l_stop) of ``width`` multipoles covering lmin <= ell <= lmax.

    l_stop is exclusive (ell = l_start, ..., l_stop - 1); the last bin stops at lmax + 1
    and may be shorter than ``width``.
    Example: multipole_bins(2, 11, 4) = [(2, 6), (6, 10), (10, 12)].
    """
    lmin, lmax, width = int(lmin), int(lmax), int(width)
    if lmin < 0 or lmax < lmin or width < 1:
        raise ValueError(
            f"lmin = {lmin}, lmax = {lmax}, width = {width}: expected 0 <= lmin <= lmax, width >= 1"
        )
    starts = range(lmin, lmax + 1, width)
    return [(start, min(start + width, lmax + 1)) for start in starts]


def bins_from_edges(edges: Sequence[int]) -> list[tuple[int, int]]:
    """Bins [edges[k], edges[k+1]) from increasing integer edges (FGBuster's ``lbins``).

    Example: bins_from_edges([2, 10, 30, 51]) = [(2, 10), (10, 30), (30, 51)], i.e. the
    last multipole used is 50.
    """
    edges = np.asarray(edges)
    if edges.ndim != 1 or edges.size < 2:
        raise ValueError(f"edges {edges}: expected at least two increasing integers")
    return _check_bins(zip(edges[:-1].tolist(), edges[1:].tolist()))


def _alm_ell_m(lmax: int, nalm: int) -> tuple[np.ndarray, np.ndarray]:
    lmax = int(lmax)
    if lmax < 0 or hp.Alm.getsize(lmax) != nalm:
        raise ValueError(
            f"a_lm of size {nalm} do not match lmax = {lmax} (expected {hp.Alm.getsize(lmax)}, "
            "healpy ordering with mmax = lmax)"
        )
    return hp.Alm.getlm(lmax)


# ===================================================================== beams, maps
def deconvolve_to_common_beam(
    alm: np.ndarray, fwhm_arcmin: float, common_fwhm_arcmin: float, lmax: int
) -> np.ndarray:
    """T, E, B a_lm (3, nalm) times b_common(ell) / b_channel(ell).

    b(ell) = ``hp.gauss_beam(fwhm, lmax, pol=True)``: column 0 (exp(-ell(ell+1) sigma^2/2))
    for T, columns 1 and 2 (the same times exp(2 sigma^2), spin 2) for E and B;
    sigma = FWHM / sqrt(8 ln 2). A FWHM of 0 means no beam (b = 1). ValueError if
    b_channel underflows to 0 at some ell <= lmax (the ratio would be undefined).
    Deconvolving to a common beam narrower than the channel's amplifies the small
    scales (and the noise) by b_common / b_channel > 1.
    """
    alm = np.asarray(alm)
    if alm.ndim != 2 or alm.shape[0] != N_STOKES:
        raise ValueError(f"alm of shape {alm.shape}: expected (3, nalm) T, E, B")
    _alm_ell_m(lmax, alm.shape[1])
    for name, value in (("fwhm_arcmin", fwhm_arcmin), ("common_fwhm_arcmin", common_fwhm_arcmin)):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} = {value}: expected a beam FWHM >= 0 arcmin")
    b_channel = hp.gauss_beam(np.radians(fwhm_arcmin / 60.0), lmax=int(lmax), pol=True)
    b_common = hp.gauss_beam(np.radians(common_fwhm_arcmin / 60.0), lmax=int(lmax), pol=True)
    if np.any(b_channel[:, :N_STOKES] <= 0):
        raise ValueError(
            f"beam of FWHM {fwhm_arcmin} arcmin underflows to 0 below lmax = {lmax}: "
            "cannot deconvolve"
        )
    ratio = b_common[:, :N_STOKES] / b_channel[:, :N_STOKES]
    return np.array([hp.almxfl(alm[i], ratio[:, i]) for i in range(N_STOKES)])


def unseen_pixels(maps: np.ndarray) -> np.ndarray:
    """(npix,) bool: pixels equal to hp.UNSEEN (``hp.mask_bad``) or not finite in any map."""
    maps = np.asarray(maps, dtype=float)
    bad = hp.mask_bad(maps) | ~np.isfinite(maps)
    return bad if bad.ndim == 1 else np.any(bad.reshape(-1, bad.shape[-1]), axis=0)


def maps_to_alm(
    maps: np.ndarray, mask: np.ndarray, lmax: int, iter: int = MAP2ALM_ITER
) -> np.ndarray:
    """T, E, B a_lm (3, nalm) of mask x (I, Q, U) maps (3, npix) [K_CMB], RING.

    UNSEEN (and non-finite) pixels are set to 0 and the maps multiplied by ``mask``
    (weights in [0, 1], e.g. :func:`spectra.apodized_mask`); then healpy's
    ``map2alm(pol=True, iter=iter, use_weights=False, use_pixel_weights=False)``, computed
    by :func:`sky.harmonics.map2alm` (pixel and ring weights would need a download).
    ValueError if the mask is non-zero on an UNSEEN pixel (the data would be silently
    zero there: build the mask with :func:`spectra.common_mask`).
    """
    maps = np.array(maps, dtype=float)
    mask = np.asarray(mask, dtype=float)
    if maps.ndim != 2 or maps.shape[0] != N_STOKES or not hp.isnpixok(maps.shape[1]):
        raise ValueError(f"maps of shape {maps.shape}: expected (3, npix) I, Q, U HEALPix maps")
    if mask.shape != maps.shape[1:]:
        raise ValueError(f"mask of shape {mask.shape}: expected ({maps.shape[1]},)")
    if not np.all(np.isfinite(mask)) or np.any(mask < 0) or np.any(mask > 1):
        raise ValueError("mask: expected weights in [0, 1]")
    bad = unseen_pixels(maps)
    if np.any(mask[bad] != 0):
        raise ValueError(
            f"mask is non-zero on {np.count_nonzero(mask[bad] != 0)} UNSEEN pixel(s): "
            "use a mask that excludes the unobserved pixels (spectra.common_mask)"
        )
    maps[:, bad] = 0.0
    maps *= mask
    return harmonics.map2alm(maps, int(lmax), iter=int(iter))


def channel_alms(
    maps: Sequence[np.ndarray],
    fwhms_arcmin: Sequence[float],
    mask: np.ndarray,
    lmax: int,
    common_fwhm_arcmin: float | None = None,
    iter: int = MAP2ALM_ITER,
) -> np.ndarray:
    """(n_channels, 3, nalm) a_lm of all channel maps, at a common beam.

    :func:`maps_to_alm` of each (3, npix) map with the same ``mask``, then
    :func:`deconvolve_to_common_beam` from its FWHM to ``common_fwhm_arcmin`` (default:
    the largest FWHM, so that no channel is deconvolved to a sharper beam).
    """
    if len(maps) != len(fwhms_arcmin):
        raise ValueError(f"{len(maps)} maps but {len(fwhms_arcmin)} beam FWHMs")
    common = float(max(fwhms_arcmin)) if common_fwhm_arcmin is None else common_fwhm_arcmin
    return np.array(
        [
            deconvolve_to_common_beam(maps_to_alm(m, mask, lmax, iter), fwhm, common, lmax)
            for m, fwhm in zip(maps, fwhms_arcmin)
        ]
    )


# ==================================================================== ILC weights
def empirical_covariance(
    alms: np.ndarray, bins, lmax: int, min_ell: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Channel covariance per bin: (C (n_bins, n_ch, n_ch), n_modes (n_bins,) int).

    alms: (n_channels, nalm) a_lm of one of T, E, B. For bin b (multipoles ell in
    [max(l_start, min_ell), l_stop)):

        C_ij(b) = sum_ell [Re(a_i,l0 a_j,l0^*) + 2 sum_{m>0} Re(a_i,lm a_j,lm^*)] / n_b,
        n_b = sum_ell (2 ell + 1)

    (n_b = 0 gives a zero matrix). ``min_ell`` = 2 excludes the ell < 2 of E and B.
    """
    alms = np.asarray(alms)
    if alms.ndim != 2:
        raise ValueError(f"alms of shape {alms.shape}: expected (n_channels, nalm)")
    ell, m = _alm_ell_m(lmax, alms.shape[1])
    bins = _check_bins(bins, lmax)
    n_ch = alms.shape[0]
    multiplicity = np.where(m == 0, 1.0, 2.0)
    cov = np.zeros((len(bins), n_ch, n_ch))
    n_modes = np.zeros(len(bins), dtype=int)
    for b, (start, stop) in enumerate(bins):
        select = (ell >= max(start, int(min_ell))) & (ell < stop)
        n_modes[b] = int(multiplicity[select].sum())  # sums of 1.0 and 2.0: exact
        if n_modes[b] == 0:
            continue
        a = alms[:, select]
        cov[b] = ((a * multiplicity[select]) @ a.conj().T).real / n_modes[b]
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))  # exactly symmetric
    return cov, n_modes


def weights_from_covariance(
    cov: np.ndarray, regularisation=None, rcond: float = DEFAULT_RCOND
) -> np.ndarray:
    """ILC weights w = C^-1 e / (e^T C^-1 e) of one (n_ch, n_ch) covariance; sum w = 1.

    C = D R D, D = diag(sqrt(C_ii)); R^-1 from its eigen-decomposition with eigenvalues
    < ``rcond`` x max discarded (pseudo-inverse). ``regularisation`` = float lambda > 0
    replaces R by R + lambda I before the inversion; None or "pinv": no loading. The
    rank checks on the number of modes are made by :func:`ilc_weights`.
    """
    cov = np.asarray(cov, dtype=float)
    n_ch = cov.shape[0]
    if cov.shape != (n_ch, n_ch) or n_ch == 0:
        raise ValueError(f"covariance of shape {cov.shape}: expected a square matrix")
    diag = np.diag(cov)
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance: non-finite entries (NaN / inf in the a_lm?)")
    if np.any(diag <= 0):
        raise ValueError(
            f"channel(s) {np.flatnonzero(diag <= 0).tolist()} have zero power in this bin: "
            "the ILC is undefined (remove the channel or the bin)"
        )
    scale = np.sqrt(diag)
    corr = cov / np.outer(scale, scale)
    if regularisation is not None and not isinstance(regularisation, str):
        loading = float(regularisation)
        if not np.isfinite(loading) or loading <= 0:
            raise ValueError(f"regularisation = {regularisation}: expected a float > 0")
        corr = corr + loading * np.eye(n_ch)
    eigval, eigvec = np.linalg.eigh(corr)
    keep = eigval > rcond * eigval[-1]
    if not np.all(keep):
        log.debug("ILC: %d of %d eigenvalues below rcond discarded", np.sum(~keep), n_ch)
    x = eigvec[:, keep] @ ((eigvec[:, keep].T @ (1.0 / scale)) / eigval[keep])
    u = x / scale  # proportional to C^+ e
    total = u.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("ILC: e^T C^+ e <= 0, the unit vector is not in the covariance range")
    return u / total


def _regularisation(regularisation):
    if regularisation is None or regularisation == "pinv":
        return regularisation
    try:
        value = float(regularisation)
    except (TypeError, ValueError):
        value = np.nan
    if not np.isfinite(value) or value <= 0:
        raise ValueError(
            f"regularisation = {regularisation!r}: expected None, 'pinv' or a float > 0"
        )
    return value


def ilc_weights(
    alms: np.ndarray,
    bins,
    lmax: int,
    regularisation=None,
    rcond: float = DEFAULT_RCOND,
    min_ell: int = 0,
) -> np.ndarray:
    """ILC weights (n_bins, n_channels) from (n_channels, nalm) a_lm of one of T, E, B.

    Per bin, w = C^-1 e / (e^T C^-1 e) with C the empirical covariance of
    :func:`empirical_covariance` (modes with ell >= ``min_ell``) and e = ones; sum w = 1.
    A bin with n_modes < n_channels has a rank-deficient covariance: ValueError unless
    ``regularisation`` is "pinv" (pseudo-inverse) or a float lambda > 0 (C + lambda
    diag(C)). See the module docstring for ``rcond``.
    """
    regularisation = _regularisation(regularisation)
    alms = np.asarray(alms)
    cov, n_modes = empirical_covariance(alms, bins, lmax, min_ell)
    n_ch = alms.shape[0]
    weights = np.empty((cov.shape[0], n_ch))
    for b, (start, stop) in enumerate(_check_bins(bins)):
        if n_modes[b] < n_ch and regularisation is None:
            raise ValueError(
                f"multipole bin [{start}, {stop}) has {n_modes[b]} modes (ell >= {min_ell}), "
                f"fewer than the {n_ch} channels: its empirical covariance is rank-deficient. "
                "Use wider bins, or regularisation='pinv' or a diagonal loading > 0"
            )
        if n_modes[b] == 0:
            raise ValueError(f"multipole bin [{start}, {stop}) has no modes (ell >= {min_ell})")
        try:
            weights[b] = weights_from_covariance(cov[b], regularisation, rcond)
        except ValueError as error:
            raise ValueError(f"multipole bin [{start}, {stop}): {error}") from error
    return weights


def weights_per_ell(weights: np.ndarray, bins, lmax: int) -> np.ndarray:
    """(lmax + 1, n_channels) weights of each multipole; rows outside every bin are 0."""
    weights = np.asarray(weights, dtype=float)
    bins = _check_bins(bins, lmax)
    if weights.ndim != 2 or weights.shape[0] != len(bins):
        raise ValueError(f"weights of shape {weights.shape}: expected ({len(bins)}, n_channels)")
    out = np.zeros((int(lmax) + 1, weights.shape[1]))
    for b, (start, stop) in enumerate(bins):
        out[start:stop] = weights[b]
    return out


def apply_weights(alms: np.ndarray, weights: np.ndarray, bins, lmax: int) -> np.ndarray:
    """sum_i w_i(b(ell)) a_i,lm: (nalm,) from (n_channels, nalm) and (n_bins, n_channels).

    a_lm with ell outside every bin are set to 0.
    """
    alms = np.asarray(alms)
    if alms.ndim != 2:
        raise ValueError(f"alms of shape {alms.shape}: expected (n_channels, nalm)")
    ell, _ = _alm_ell_m(lmax, alms.shape[1])
    w_ell = weights_per_ell(weights, bins, lmax)
    if w_ell.shape[1] != alms.shape[0]:
        raise ValueError(f"{w_ell.shape[1]} weights per bin for {alms.shape[0]} channels")
    return np.einsum("in,ni->n", alms, w_ell[ell])


def _check_channel_alms(alms: np.ndarray) -> np.ndarray:
    alms = np.asarray(alms)
    if alms.ndim != 3 or alms.shape[1] != N_STOKES:
        raise ValueError(f"alms of shape {alms.shape}: expected (n_channels, 3, nalm) T, E, B")
    return alms


def harmonic_ilc(
    alms: np.ndarray,
    bins,
    lmax: int,
    regularisation=None,
    rcond: float = DEFAULT_RCOND,
) -> tuple[np.ndarray, np.ndarray]:
    """HILC of (n_channels, 3, nalm) T, E, B a_lm (common beam, K_CMB).

    Returns (alm_cmb (3, nalm), weights (3, n_bins, n_channels)): T, E and B are
    combined independently (:func:`ilc_weights`, :func:`apply_weights`); the E and B
    covariances use ell >= 2 only. Apply the same weights to other inputs with
    :func:`apply_ilc`.
    """
    alms = _check_channel_alms(alms)
    weights = np.array(
        [
            ilc_weights(
                alms[:, s],
                bins,
                lmax,
                regularisation,
                rcond,
                min_ell=0 if s == 0 else MIN_ELL_POL,
            )
            for s in range(N_STOKES)
        ]
    )
    return apply_ilc(alms, weights, bins, lmax), weights


def apply_ilc(alms_components: np.ndarray, weights: np.ndarray, bins, lmax: int) -> np.ndarray:
    """(3, nalm) T, E, B: the HILC ``weights`` (3, n_bins, n_channels) applied to
    (n_channels, 3, nalm) a_lm, e.g. the foreground-only or noise-only a_lm of the
    channels, to get their residual in the CMB estimate."""
    alms = _check_channel_alms(alms_components)
    weights = np.asarray(weights, dtype=float)
    if weights.ndim != 3 or weights.shape[0] != N_STOKES:
        raise ValueError(f"weights of shape {weights.shape}: expected (3, n_bins, n_channels)")
    return np.array([apply_weights(alms[:, s], weights[s], bins, lmax) for s in range(N_STOKES)])


def merge_bins_for_modes(bins, fsky: float, n_channels: int, min_modes_per_channel: float):
    """Merge consecutive bins, from the lowest ell up, until each holds at least
    ``min_modes_per_channel x n_channels`` effective modes, f_sky sum (2 ell + 1).

    With N effective modes the empirical covariance of n channels biases the ILC by
    ~ -(n - 1) / N (Delabrouille et al. 2009) and makes its weights noisy: on a small
    sky fraction the lowest bins need to be wide. A short last bin joins the one before.
    """
    bins = _check_bins(bins)
    needed = min_modes_per_channel * n_channels
    merged: list[tuple[int, int]] = []
    start = bins[0][0]
    for _, stop in bins:
        modes = fsky * sum(2 * ell + 1 for ell in range(start, stop))
        if modes >= needed:
            merged.append((start, stop))
            start = stop
    if start < bins[-1][1]:
        if merged:
            merged[-1] = (merged[-1][0], bins[-1][1])
        else:
            merged.append((start, bins[-1][1]))
    return merged
