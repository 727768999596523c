"""Masks and pseudo-C_ell angular power spectra with an f_sky (w2) correction.

Conventions: HEALPix RING maps in Galactic coordinates, (3, npix) I Q U in K_CMB with
unobserved pixels = hp.UNSEEN; masks are (npix,) arrays, True / 1 = pixel kept; spectra
are C_ell (not D_ell) in K_CMB^2, ordered TT, EE, BB, TE, EB, TB (``hp.alm2cl``);
multipole bins are half-open [l_start, l_stop) pairs (:func:`hilc.multipole_bins`).

Estimator
---------
For the a_lm of the masked map (mask W, :func:`hilc.maps_to_alm`), the pseudo spectrum
is

    C~_ell = (1 / (2 ell + 1)) sum_m |a~_lm|^2,      C_ell estimate = C~_ell / w2,
    w2 = mean over the sphere of W^2

(:func:`pseudo_spectra`). <C~_ell> = sum_l' M_ll' C_l', and sum_l' M_ll' = w2 (for a
signal whose C_ell is smooth on the scale of the mask's own spectrum), so dividing by w2
is unbiased for white noise and for spectra that vary slowly with ell; the mode coupling
is not deconvolved. The effective number of modes for a likelihood is
f_sky (2 ell + 1) with f_sky = w2^2 / w4 (:func:`fsky_weights`).

Why healpy (``hp.map2alm`` / ``hp.alm2cl``) divided by w2 and not NaMaster
-----------------------------------------------------------------------
NaMaster (``pymaster`` on PyPI) would deconvolve the mode-coupling matrix of the mask
and can purify E and B. Neither is needed at the precision of this study, which
compares the BB spectra of residual maps (recovered CMB - input CMB) between
simulations with and without the HWPSS x TES-nonlinearity systematic, computed with the
same mask and the same estimator, so that mask effects largely cancel in their ratio.
Honest limitations of the simple estimator:

* mask-induced E -> B leakage is not removed. Measured with this module (nside 64,
  Galactic cut 20 deg, apodisation 5 deg, pure-E input with a flat or an ell^-2.4
  spectrum): pseudo-BB / pseudo-EE = 0.16-0.21 for 2 <= ell < 10, 0.04-0.09 for
  10 <= ell < 30, 0.02-0.03 for 30 <= ell < 60 and < 0.01 above. The residual maps are
  dominated by noise and foreground residuals, whose E and B powers are comparable
  (equal for white noise, BB / EE ~ 0.2-0.5 for synchrotron and dust), so above
  ell ~ 10 the leaked power is a few per cent of the BB being measured (unlike for the
  CMB itself, whose EE exceeds the lensing BB by two orders of magnitude); at
  ell < 10 (reionisation bump) it is a 20-50 % bias that largely cancels only in a
  ratio of residual spectra with similar E / B content. A residual dominated by E
  (e.g. a systematic that is mostly E) has its pseudo-BB overestimated: an upper bound;
* the mode coupling is not deconvolved: the w2 correction is exact in expectation only
  for spectra that are smooth over the mask's coupling width (delta ell ~ 180 deg /
  apodisation scale); steep spectra (foregrounds ~ ell^-2.4 at low ell) are smoothed and
  the lowest multipoles biased;
* no pixel-window correction is applied (the same for every spectrum compared); the
  common Gaussian beam of the HILC is deconvolved (:func:`deconvolve_beam`), so that
  residual spectra and the model's C_lens and C_GW are at the same (unit) beam, as
  FGBuster's ``harmonic_ilc`` does by deconvolving each channel's beam;
* inhomogeneous noise is treated as homogeneous: the estimate is the W^2-weighted mean
  of the local noise power.

NaMaster would add a compiled dependency (C library, GSL, FFTW) and the cost of the
mode-coupling matrices, for effects that are second order in a residual-spectrum
ratio. This is also what FGBuster's ``harmonic_ilc`` does (anafast spectra divided by
an f_sky).
"""

from __future__ import annotations

from collections.abc import Sequence

import healpy as hp
import numpy as np

from .hilc import _check_bins, unseen_pixels

SPECTRA_NAMES = ("TT", "EE", "BB", "TE", "EB", "TB")  # hp.alm2cl order for T, E, B
N_STOKES = 3
SMOOTHING_ITER = 3  # Jacobi iterations of the map2alm inside hp.smoothing


# ============================================================================= masks
def galactic_mask(nside: int, galactic_cut_deg: float) -> np.ndarray:
    """(npix,) bool, RING, Galactic: True where |b| >= ``galactic_cut_deg`` (kept).

    Uses the pixel centres: |b| >= cut <=> |z| >= sin(cut), z = cos(theta) = sin(b).
    A cut of 0 keeps every pixel.
    """
    nside = int(nside)
    if not hp.isnsideok(nside):
        raise ValueError(f"nside = {nside}: expected a power of 2")
    cut = float(galactic_cut_deg)
    if not 0 <= cut <= 90:
        raise ValueError(f"galactic_cut_deg = {galactic_cut_deg}: expected 0 <= cut <= 90")
    if cut == 0:
        return np.ones(hp.nside2npix(nside), dtype=bool)
    z = hp.pix2vec(nside, np.arange(hp.nside2npix(nside)))[2]
    return np.abs(z) >= np.sin(np.radians(cut))


def common_mask(
    maps: Sequence[np.ndarray], galactic_cut_deg: float, region_nside: int | None = None
) -> np.ndarray:
    """(npix,) bool: pixels observed in EVERY map (no UNSEEN / non-finite value in any of
    its I, Q, U) and with |b| >= ``galactic_cut_deg`` (:func:`galactic_mask`).

    ``region_nside`` (at most the maps' nside): the region is decided on that coarser
    grid, then returned at the maps' resolution: a coarse pixel is kept if its centre
    passes the cut and every map pixel inside it is observed in every map. The region is
    then the same at every map resolution (a coarse pixel is a union of fine ones).
    """
    if len(maps) == 0:
        raise ValueError("common_mask: expected at least one map")
    npix = np.shape(maps[0])[-1]
    if not hp.isnpixok(npix):
        raise ValueError(f"maps with {npix} pixels: not a HEALPix map")
    keep = np.ones(npix, dtype=bool)
    for k, m in enumerate(maps):
        if np.shape(m)[-1] != npix:
            raise ValueError(f"map {k} has {np.shape(m)[-1]} pixels, map 0 has {npix}")
        keep &= ~unseen_pixels(m)
    nside = hp.npix2nside(npix)
    if region_nside is None or region_nside == nside:
        return keep & galactic_mask(nside, galactic_cut_deg)
    if not hp.isnsideok(region_nside) or region_nside > nside:
        raise ValueError(
            f"region_nside = {region_nside}: expected a power of 2 at most the maps' nside {nside}"
        )
    # ud_grade averages the fine pixels of each coarse one: 1 where every one is kept
    all_observed = hp.ud_grade(keep.astype(float), region_nside) == 1.0
    coarse = all_observed & galactic_mask(region_nside, galactic_cut_deg)
    return hp.ud_grade(coarse.astype(float), nside) == 1.0


def apodized_mask(
    binary_mask: np.ndarray, apodization_deg: float, method: str = "rescaled"
) -> np.ndarray:
    """(npix,) float mask in [0, 1], zero on the pixels excluded by ``binary_mask``.

    s = ``hp.smoothing`` of the binary mask with a Gaussian of FWHM ``apodization_deg``
    (lmax = 3 nside - 1, no pixel or ring weights, 3 Jacobi iterations: with none the
    quadrature error of a sharp mask leaves s ~ 0.993 instead of 1 far from the edges
    at nside 64), then

    * method "rescaled" (default): W = clip(2 s - 1, 0, 1) x binary. Near a straight
      edge s = (1 + erf(x / (sqrt(2) sigma))) / 2 at a distance x inside the kept region,
      so W = erf(x / (sqrt(2) sigma)) is continuous: 0 at the edge, 0.99 at
      x = 2.6 sigma = 1.1 FWHM;
    * method "product": W = clip(s, 0, 1) x binary. Simpler, but W jumps from ~0.5 to 0
      at the edge (s = 1/2 there), which leaves part of the ringing of a hard mask.

    Holes much smaller than the FWHM are barely apodised by either method (s stays close
    to 1 around them). ``apodization_deg`` = 0 returns the binary mask as float.
    """
    binary = np.asarray(binary_mask)
    if binary.ndim != 1 or not hp.isnpixok(binary.size):
        raise ValueError(f"binary_mask of shape {binary.shape}: expected a (npix,) HEALPix mask")
    if binary.dtype != bool:
        if not np.all(np.isin(binary, (0, 1))):
            raise ValueError("binary_mask: expected booleans or 0 / 1 values")
        binary = binary.astype(bool)
    apodization_deg = float(apodization_deg)
    if not np.isfinite(apodization_deg) or apodization_deg < 0:
        raise ValueError(f"apodization_deg = {apodization_deg}: expected >= 0")
    if method not in ("rescaled", "product"):
        raise ValueError(f"method = {method!r}: expected 'rescaled' or 'product'")
    binary_float = binary.astype(float)
    if apodization_deg == 0:
        return binary_float
    smoothed = hp.smoothing(
        binary_float,
        fwhm=np.radians(apodization_deg),
        iter=SMOOTHING_ITER,
        use_weights=False,
        use_pixel_weights=False,
    )
    if method == "rescaled":
        smoothed = 2.0 * smoothed - 1.0
    return np.clip(smoothed, 0.0, 1.0) * binary_float


def fsky_weights(mask: np.ndarray) -> dict[str, float]:
    """Sky fractions of a mask W: {"fsky": mean W, "w2": mean W^2, "w4": mean W^4,
    "fsky_eff": w2^2 / w4}.

    w2 is the pseudo-C_ell normalisation (:func:`pseudo_spectra`); fsky_eff is the
    fraction for the effective number of modes, fsky_eff (2 ell + 1), in a likelihood.
    """
    mask = np.asarray(mask, dtype=float)
    if mask.ndim != 1 or not np.all(np.isfinite(mask)) or np.any(mask < 0):
        raise ValueError("mask: expected a (npix,) array of finite weights >= 0")
    w2 = float(np.mean(mask**2))
    w4 = float(np.mean(mask**4))
    return {
        "fsky": float(np.mean(mask)),
        "w2": w2,
        "w4": w4,
        "fsky_eff": w2**2 / w4 if w4 > 0 else 0.0,
    }


# =========================================================================== spectra
def pseudo_spectra(
    alm: np.ndarray, lmax: int, w2: float, alm2: np.ndarray | None = None
) -> np.ndarray:
    """(6, lmax + 1) TT, EE, BB, TE, EB, TB [K_CMB^2] = ``hp.alm2cl`` / w2.

    ``alm``: T, E, B a_lm (3, nalm) of a masked map (:func:`hilc.maps_to_alm`); ``w2`` =
    mean(W^2) of the mask (:func:`fsky_weights`; 1 for the full sky). With ``alm2`` the
    cross spectra of ``alm`` and ``alm2``. See the module docstring for what the w2
    correction does and does not correct.
    """
    alm = np.asarray(alm)
    lmax = int(lmax)
    if alm.ndim != 2 or alm.shape[0] != N_STOKES or alm.shape[1] != hp.Alm.getsize(lmax):
        raise ValueError(
            f"alm of shape {alm.shape}: expected (3, {hp.Alm.getsize(lmax)}) T, E, B at "
            f"lmax = {lmax}"
        )
    if alm2 is not None and np.shape(alm2) != alm.shape:
        raise ValueError(f"alm2 of shape {np.shape(alm2)}: expected {alm.shape}")
    w2 = float(w2)
    if not np.isfinite(w2) or w2 <= 0:
        raise ValueError(f"w2 = {w2}: expected a mask normalisation > 0")
    cl = hp.alm2cl(alm, alm2, lmax=lmax, mmax=lmax)
    return np.asarray(cl) / w2


def deconvolve_beam(cl: np.ndarray, fwhm_arcmin: float) -> np.ndarray:
    """C_ell / (b_X b_Y) for TT, EE, BB, TE, EB, TB (6, lmax + 1) [K_CMB^2]: the spectra of
    maps smoothed by a Gaussian beam of ``fwhm_arcmin``, brought to unit beam.

    b = ``hp.gauss_beam(fwhm, lmax, pol=True)``: column 0 for T, columns 1 and 2 (spin 2)
    for E and B. Applied to every residual spectrum with the HILC's common beam, so that
    C_res, N_ell and C_FGres are on the same footing as the unbeamed C_lens and C_GW."""
    cl = np.asarray(cl, dtype=float)
    if cl.ndim != 2 or cl.shape[0] != len(SPECTRA_NAMES):
        raise ValueError(f"cl of shape {cl.shape}: expected (6, lmax + 1) TT EE BB TE EB TB")
    beam = hp.gauss_beam(np.radians(fwhm_arcmin / 60.0), lmax=cl.shape[1] - 1, pol=True)
    t, e, b = beam[:, 0], beam[:, 1], beam[:, 2]
    return cl / np.array([t * t, e * e, b * b, t * e, e * b, t * b])


def bin_centres(bins) -> np.ndarray:
    """(n_bins,) (2 ell + 1)-weighted mean multipole of each bin [l_start, l_stop)."""
    bins = _check_bins(bins)
    out = np.empty(len(bins))
    for b, (start, stop) in enumerate(bins):
        ell = np.arange(start, stop, dtype=float)
        out[b] = np.sum(ell * (2 * ell + 1)) / np.sum(2 * ell + 1)
    return out


def binned_spectrum(cl: np.ndarray, bins) -> tuple[np.ndarray, np.ndarray]:
    """(centres (n_bins,), binned (..., n_bins)): C_b = sum_ell (2 ell + 1) C_ell /
    sum_ell (2 ell + 1) over each bin [l_start, l_stop) (last axis of ``cl`` = ell from
    0); centres from :func:`bin_centres`."""
    cl = np.asarray(cl, dtype=float)
    bins = _check_bins(bins)
    if cl.ndim == 0 or bins[-1][1] > cl.shape[-1]:
        raise ValueError(
            f"cl with {cl.shape[-1] if cl.ndim else 0} multipoles: the bins end at "
            f"ell = {bins[-1][1] - 1}"
        )
    binned = np.empty(cl.shape[:-1] + (len(bins),))
    for b, (start, stop) in enumerate(bins):
        weight = 2.0 * np.arange(start, stop) + 1.0
        binned[..., b] = np.sum(cl[..., start:stop] * weight, axis=-1) / weight.sum()
    return bin_centres(bins), binned
