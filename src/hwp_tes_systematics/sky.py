"""Input sky: CMB realisations from the PTEP spectra and d0s0-like foregrounds via pysm3.

Conventions (the whole module): HEALPix RING maps in Galactic coordinates, shape
``(3, npix)`` = (I, Q, U), in K_CMB (thermodynamic temperature of the CMB black body,
T_CMB = 2.7255 K), a_lm in healpy ordering (``hp.Alm.getidx``), angular power spectra
C_ell (not D_ell = ell (ell + 1) C_ell / 2 pi) in K_CMB^2, ordered (TT, EE, BB, TE).

CMB
---
The spectra are the two files shipped inside litebird_sim (``litebird_sim/datautils``)::

    Cls_Planck2018_for_PTEP_2020_r0.fits         scalar + lensing, r = 0
    Cls_Planck2018_for_PTEP_2020_tensor_r1.fits  tensor modes only, r = 1

What the files hold (inspected, healpy ``read_cl``): one binary table, 4001 rows
(ell = 0..4000), columns TEMPERATURE, GRADIENT, CURL, G-T = TT, EE, BB, TE; values are
C_ell (not D_ell) in uK_CMB^2 (litebird_sim multiplies them by 1e-12 to get K^2).
Checks: r0 TT at ell = 2 is 1069 uK^2, i.e. D_2 = 1021 uK^2; the lensing BB gives
D_1000 = 0.097 uK^2; the tensor file (r = 1) gives D_80^BB = 0.065 uK^2 (so
6.5e-4 uK^2 for r = 0.01), has TT, EE and TE tensor contributions too, and its BB at
ell = 1000 is 1 % of the lensing BB (no lensing in it). The model spectrum is

    C_ell(r) = C_ell^{r0} + r C_ell^{tensor, r=1}     (all four spectra).

Realisation ``seed`` of the CMB is drawn from ``seeding.rng(master_seed, "cmb", seed)``,
the same for every channel; the draws are ordered by increasing ell, so the a_lm with
ell <= lmax do not depend on lmax (a lower lmax gives the same large scales).

Foregrounds
-----------
Two components with the SEDs of the pysm3 presets d0 and s0 (constant spectral
parameters over the sky): modified black body dust, beta_d = 1.54, T_d = 20 K, and
power-law synchrotron, beta_s = -3, in Rayleigh-Jeans brightness temperature:

    T_RJ^dust(nu) = T_RJ^dust(nu_0) (nu / nu_0)^(beta_d - 2) B_nu(T_d) / B_nu0(T_d)
    T_RJ^sync(nu) = T_RJ^sync(nu_0) (nu / nu_0)^beta_s

The templates T(nu_0) are either

* the pysm3 d0/s0 template files (``pysm_2/dust_{t,q,u}_new.fits``, I at 545 GHz and
  Q, U at 353 GHz; ``pysm_2/synch_{t,q,u}_new.fits``, I at 408 MHz and Q, U at 23 GHz) when a local pysm3 data folder is given (argument
  ``pysm_local_data`` or environment variable ``PYSM_LOCAL_DATA``); nothing is ever
  downloaded: missing files raise :class:`FileNotFoundError`; or
* EMBEDDED OFFLINE templates (flag :data:`OFFLINE_SOURCE`, "NOT pysm3 data"):
  Gaussian random fields with power-law angular spectra (constants below, with their
  sources) times a smooth Galactic-latitude envelope, fixed for a master seed and nside.

In both cases pysm3 models (``ModifiedBlackBody``, ``PowerLaw``) do the SED scaling and
the bandpass integration, and ``pysm3.bandpass_unit_conversion`` the conversion to
K_CMB. pysm3 bandpass weights multiply the specific intensity I_nu (W m^-2 Hz^-1 sr^-1).
A single-mode, single-polarisation detector of transmission w(nu) receives
P = integral w(nu) (c^2 / 2 nu^2) I_nu d nu (see :mod:`radiometry`), so the pysm3
weights are w(nu) / nu^2 (``single_mode=True``, the default). The map then holds

    T_CMB-equivalent = integral w T_RJ d nu / integral w (dT_RJ / dT_CMB) d nu,

exactly the temperature whose power is dP/dT x T with the dP/dT of
:func:`radiometry.dpower_dtemperature_w_per_k`. ``single_mode=False`` passes w(nu)
unchanged (the pysm3 / litebird_sim convention of a constant-etendue detector).

With constant spectral parameters the band-integrated emission is the template times
one factor per Stokes parameter; the factors are obtained by evaluating the same pysm3
model on unit templates, which is exact and avoids integrating all pixels at the 2001
samples of a band (checked against the full-map pysm3 evaluation in the tests).
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import healpy as hp
import numpy as np

from . import seeding
from .io import atomic_path
from .radiometry import Bandpass, channel_bandpass

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- CMB
CMB_SCALAR_FILE = "Cls_Planck2018_for_PTEP_2020_r0.fits"  # scalar + lensing, r = 0
CMB_TENSOR_FILE = "Cls_Planck2018_for_PTEP_2020_tensor_r1.fits"  # tensor only, r = 1
UK2_TO_K2 = 1e-12  # the files are in uK_CMB^2
SPECTRA_ORDER = ("TT", "EE", "BB", "TE")

# --------------------------------------------------------------- foregrounds: SEDs
# pysm3 presets d0 / s0 (pysm3/data/presets.cfg): beta_d = 1.54, T_d = 20 K, beta_s = -3.
DUST_BETA = 1.54
DUST_TEMPERATURE_K = 20.0
SYNC_BETA = -3.0
DUST_FREQ_REF_GHZ = 353.0  # offline dust template frequency (I, Q, U)
SYNC_FREQ_REF_GHZ = 23.0  # offline synchrotron template frequency (I, Q, U), WMAP K band

# ----------------------------------------------- foregrounds: offline templates
# Power-law spectra C_ell^XY = C_80^XY (ell / 80)^alpha_XY for ell >= 2 (zero below),
# normalised by the pivot amplitude D_80^EE = 80 x 81 C_80^EE / 2 pi. The amplitudes
# are those of the faint high-latitude sky: the Galactic envelope (1 at the poles,
# rising towards the plane) multiplies the random field, so the full-sky spectra are
# larger and dominated by low latitudes.
ELL_PIVOT = 80
# Dust, at 353 GHz.
# Planck 2018 results XI (A&A 641, A11), power-law fits for its largest region LR71:
# alpha_EE = -2.42, alpha_BB = -2.54; A_BB / A_EE about 0.5 (E/B asymmetry); T-E
# correlation ratio r_TE = TE / sqrt(TT EE) = 0.357 (values recalled, order of magnitude).
DUST_ALPHA_EE = -2.42
DUST_ALPHA_BB = -2.54
DUST_ALPHA_TT = -2.42  # assumption: same slope as EE (keeps r_TE constant with ell)
DUST_BB_OVER_EE = 0.5
DUST_R_TE = 0.357
# D_80^EE at 353 GHz in uK_CMB^2 at the poles: of the order of the Planck 2018 XI
# amplitude for its cleanest regions (tens of uK_CMB^2); assumption. Converted to uK_RJ^2.
DUST_D80_EE_UK_CMB2 = 40.0
# Mean dust intensity at the poles at 353 GHz: N_H ~ 1.5e20 cm^-2 and an emissivity of
# ~0.045 MJy/sr per 1e20 cm^-2 (Planck 2013 XI) give ~0.07 MJy/sr ~ 20 uK_RJ; assumption.
DUST_I_POLE_UK_RJ = 20.0
DUST_PLANE_CORE_DEG = 3.0  # envelope core (see galactic_envelope); plane / pole ~ 19; assumption
# Synchrotron, at 23 GHz.
# Martire, Barreiro & Martinez-Gonzalez 2022 (JCAP, arXiv:2110.12803), WMAP K + Planck
# 30 GHz: alpha_EE = -2.95, alpha_BB = -2.85, B/E = 0.22, EB ~ 0; slopes rounded to -3.
SYNC_ALPHA_EE = -3.0
SYNC_ALPHA_BB = -3.0
SYNC_ALPHA_TT = -3.0  # assumption
SYNC_BB_OVER_EE = 0.22
SYNC_R_TE = 0.0  # assumption: no T-E correlation
# D_80^EE at 23 GHz in uK_RJ^2 at the poles: order of the WMAP K-band high-latitude
# polarisation (gives a polarisation fraction of ~20 % at the poles); assumption.
SYNC_D80_EE_UK_RJ2 = 3.0
# Mean synchrotron intensity at the poles at 23 GHz: ~10 K of Galactic emission at
# 408 MHz (Haslam et al. 1982, high-latitude minimum minus CMB and extragalactic
# background) scaled with beta_s = -3 gives ~56 uK_RJ; assumption.
SYNC_I_POLE_UK_RJ = 60.0
SYNC_PLANE_CORE_DEG = 5.0  # envelope core; plane / pole ~ 11; assumption
# Intensity: I = e(b) (I_pole + dT), with the TT amplitude set so that
# rms(dT) = INTENSITY_RMS_FRACTION x I_pole (sum over 2 <= ell <= ELL_MAX_RMS), so that
# the intensity stays positive (assumption; for dust, Planck's TE / EE = 2.76 with
# r_TE = 0.357 would imply TT / EE = 60 and, with alpha = -2.42 down to ell = 2, an rms
# of 65 % of I_pole: negative over ~9 % of the sky). TE = r_TE sqrt(TT EE).
INTENSITY_RMS_FRACTION = 0.3
ELL_MAX_RMS = 4096
# Safety floor of I_pole + dT at this fraction of I_pole (reached on ~1e-3 of the sky).
INTENSITY_FLOOR_FRACTION = 0.1

# --------------------------------------------------------------- flags and files
PYSM_SOURCE = "pysm3 d0s0 templates"
OFFLINE_SOURCE = "embedded offline power-law templates (NOT pysm3 data)"
PYSM_PRESETS = {"dust": "d0", "synchrotron": "s0"}
COMPONENTS = ("dust", "synchrotron")
FOREGROUND_SOURCE_KEY = "FGSOURCE"  # FITS header key of the foreground flag
MAP_UNIT = "K_CMB"
# Polarisation convention of every map written or read here: COSMO, the one healpy's
# spin-2 transforms and litebird_sim's data model assume. The IAU convention counts the
# polarisation angle the other way: U of opposite sign (POLCCONV = 'IAU' on input).
POLARISATION_CONVENTION = "COSMO"
N_STOKES = 3


# =============================================================================== CMB
def _litebird_sim_datautils() -> Path:
    """``<litebird_sim package>/datautils``, found without importing litebird_sim."""
    spec = importlib.util.find_spec("litebird_sim")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("litebird_sim is not installed: its CMB spectra are needed")
    return Path(next(iter(spec.submodule_search_locations))) / "datautils"


@functools.lru_cache(maxsize=2)
def _read_spectra_k2(filename: str) -> np.ndarray:
    """(4, 4001) C_ell in K_CMB^2 (TT, EE, BB, TE) from a litebird_sim spectra file."""
    path = _litebird_sim_datautils() / filename
    if not path.is_file():
        raise FileNotFoundError(f"{path}: CMB spectra file not found in litebird_sim")
    cls = np.asarray(hp.read_cl(str(path)), dtype=float) * UK2_TO_K2
    if cls.ndim != 2 or cls.shape[0] != 4:
        raise ValueError(f"{path}: expected 4 spectra (TT, EE, BB, TE), got shape {cls.shape}")
    cls.flags.writeable = False
    return cls


def _spectra(filename: str, lmax: int) -> np.ndarray:
    cls = _read_spectra_k2(filename)
    lmax = int(lmax)
    if not 0 <= lmax < cls.shape[1]:
        raise ValueError(
            f"lmax = {lmax}: the spectra in {filename} cover 0 <= lmax <= {cls.shape[1] - 1}"
        )
    return cls[:, : lmax + 1].copy()


def lensing_bb(lmax: int) -> np.ndarray:
    """Lensing C_ell^BB [K_CMB^2], ell = 0..lmax: the BB of the r = 0 PTEP file."""
    return _spectra(CMB_SCALAR_FILE, lmax)[2]


def tensor_bb_r1(lmax: int) -> np.ndarray:
    """Primordial tensor C_ell^BB for r = 1 [K_CMB^2], ell = 0..lmax (no lensing)."""
    return _spectra(CMB_TENSOR_FILE, lmax)[2]


def cmb_spectra(r: float, lmax: int) -> np.ndarray:
    """C_ell(r) = C_ell^{r0} + r C_ell^{tensor, r=1}, shape (4, lmax + 1), TT EE BB TE [K_CMB^2].

    C_ell, not D_ell; the r0 file holds scalar + lensing spectra, the tensor file the
    tensor spectra for r = 1 (TT, EE, BB, TE); see the module docstring.
    """
    if not np.isfinite(r) or r < 0:
        raise ValueError(f"r = {r}: expected a finite tensor-to-scalar ratio >= 0")
    return _spectra(CMB_SCALAR_FILE, lmax) + float(r) * _spectra(CMB_TENSOR_FILE, lmax)


def _ell_major_lm(lmax: int) -> tuple[np.ndarray, np.ndarray]:
    """(ell, m) of all 0 <= m <= ell <= lmax ordered by ell then m."""
    ell = np.repeat(np.arange(lmax + 1), np.arange(1, lmax + 2))
    first = ell * (ell + 1) // 2
    m = np.arange(ell.size) - first
    return ell, m


def gaussian_alm(cls: np.ndarray, lmax: int, rng: np.random.Generator) -> np.ndarray:
    """Gaussian a_lm (3, nalm) complex (T, E, B) with spectra ``cls`` = (TT, EE, BB, TE).

    For each ell, with z1, z2, z3 independent unit normal variates,

        a_T = sqrt(TT) z1
        a_E = (TE / sqrt(TT)) z1 + sqrt(EE - TE^2 / TT) z2     (Cholesky of [[TT, TE], [TE, EE]])
        a_B = sqrt(BB) z3

    so <|a_Xlm|^2> = C_ell^XX and <a_Tlm a_Elm^*> = C_ell^TE. m = 0 modes are real
    (z ~ N(0, 1), variance C_ell); m > 0 modes are complex, z = (x + i y) / sqrt(2) with
    x, y ~ N(0, 1) (variance C_ell / 2 per real and imaginary part). Units: sqrt of the
    units of ``cls``. ``cls`` may extend beyond lmax (truncated). The variates come from
    ``rng`` in order of increasing ell (then m), so a realisation at a lower lmax is the
    same as the ell <= lmax part of one at a higher lmax. Output in healpy ordering.
    """
    lmax = int(lmax)
    cls = np.asarray(cls, dtype=float)
    if lmax < 0 or cls.ndim != 2 or cls.shape[0] != 4 or cls.shape[1] < lmax + 1:
        raise ValueError(
            f"cls of shape {cls.shape}, lmax = {lmax}: expected (4, >= lmax + 1) "
            "spectra TT, EE, BB, TE"
        )
    tt, ee, bb, te = cls[:, : lmax + 1]
    if np.any(tt < 0) or np.any(ee < 0) or np.any(bb < 0):
        raise ValueError("cls: TT, EE and BB must be >= 0")
    sqrt_tt = np.sqrt(tt)
    with np.errstate(divide="ignore", invalid="ignore"):
        l_te = np.where(tt > 0, te / np.where(tt > 0, sqrt_tt, 1.0), 0.0)
    residual = ee - l_te**2
    if np.any(residual < -1e-10 * np.maximum(ee, np.finfo(float).tiny)):
        raise ValueError("cls: TE^2 > TT EE at some ell (not a covariance)")
    l_ee = np.sqrt(np.clip(residual, 0.0, None))
    sqrt_bb = np.sqrt(bb)

    ell, m = _ell_major_lm(lmax)
    draws = rng.standard_normal((ell.size, 3, 2))
    z = np.where(
        (m == 0)[:, None],
        draws[..., 0] + 0j,
        (draws[..., 0] + 1j * draws[..., 1]) / np.sqrt(2.0),
    )  # (n, 3)
    index = hp.Alm.getidx(lmax, ell, m)
    alm = np.zeros((3, ell.size), dtype=complex)
    alm[0, index] = sqrt_tt[ell] * z[:, 0]
    alm[1, index] = l_te[ell] * z[:, 0] + l_ee[ell] * z[:, 1]
    alm[2, index] = sqrt_bb[ell] * z[:, 2]
    return alm


def _check_fwhm(fwhm_arcmin: float) -> float:
    fwhm_arcmin = float(fwhm_arcmin)
    if not np.isfinite(fwhm_arcmin) or fwhm_arcmin < 0:
        raise ValueError(f"fwhm_arcmin = {fwhm_arcmin}: expected a beam FWHM >= 0 arcmin")
    return fwhm_arcmin


def smooth_alm(alm: np.ndarray, fwhm_arcmin: float, lmax: int) -> np.ndarray:
    """T, E, B a_lm times the Gaussian beam window B_ell of FWHM ``fwhm_arcmin``.

    B_ell = exp(-ell (ell + 1) sigma^2 / 2), sigma = FWHM / sqrt(8 ln 2), with the spin-2
    factor exp(2 sigma^2) for E and B (``healpy.gauss_beam(pol=True)``). 0 = no beam.
    """
    fwhm_arcmin = _check_fwhm(fwhm_arcmin)
    if fwhm_arcmin == 0:
        return np.array(alm, copy=True)
    beam = hp.gauss_beam(np.radians(fwhm_arcmin / 60.0), lmax=lmax, pol=True)
    return np.array([hp.almxfl(alm[i], beam[:, i]) for i in range(N_STOKES)])


def cmb_alm(lmax: int, r: float, master_seed: int, seed: int) -> np.ndarray:
    """a_lm (3, nalm) [K_CMB] of CMB realisation ``seed``: rng names ("cmb", seed).

    The same for every channel; its ell <= l part does not depend on lmax >= l.
    """
    cls = cmb_spectra(r, lmax)
    return gaussian_alm(cls, lmax, seeding.rng(master_seed, "cmb", int(seed)))


def cmb_map(
    nside: int, lmax: int, r: float, master_seed: int, seed: int, fwhm_arcmin: float = 0.0
) -> np.ndarray:
    """CMB realisation ``seed``, (3, npix) I Q U [K_CMB], RING, Galactic.

    Gaussian beam of FWHM ``fwhm_arcmin`` (0 = none), no pixel window (``pixwin=False``).
    """
    _check_nside(nside)
    alm = smooth_alm(cmb_alm(lmax, r, master_seed, seed), fwhm_arcmin, lmax)
    return hp.alm2map(alm, int(nside), lmax=int(lmax), pixwin=False)


def _check_nside(nside: int) -> int:
    if not hp.isnsideok(int(nside)) or int(nside) != nside:
        raise ValueError(f"nside = {nside}: expected a power of 2")
    return int(nside)


# ======================================================================= foregrounds
def galactic_envelope(nside: int, core_deg: float) -> np.ndarray:
    """Smooth latitude envelope e(b) = sqrt((1 + s^2) / (sin^2 b + s^2)), s = sin(core).

    A cosecant law (a plane-parallel slab: column density ~ 1 / |sin b|) with a core of
    half-width ``core_deg`` at the plane: e = 1 at the poles, sqrt(1 + s^2) / s at b = 0.
    """
    sin_b = hp.pix2vec(_check_nside(nside), np.arange(hp.nside2npix(nside)))[2]
    s2 = np.sin(np.radians(core_deg)) ** 2
    return np.sqrt((1.0 + s2) / (sin_b**2 + s2))


def power_law_spectra(
    d80_ee: float,
    alpha_ee: float,
    alpha_bb: float,
    alpha_tt: float,
    bb_over_ee: float,
    rms_tt: float,
    r_te: float,
    lmax: int,
) -> np.ndarray:
    """(4, lmax + 1) power-law spectra TT, EE, BB, TE, zero at ell < 2.

        C_ell^EE = C_80 (ell / 80)^alpha_EE,   C_80 = 2 pi d80_ee / (80 x 81)
        C_ell^BB = bb_over_ee C_80 (ell / 80)^alpha_BB
        C_ell^TT = A_TT (ell / 80)^alpha_TT,   A_TT such that
                   sum_{ell=2}^{ELL_MAX_RMS} (2 ell + 1) C_ell^TT / 4 pi = rms_tt^2
        C_ell^TE = r_te sqrt(C_ell^TT C_ell^EE)

    Units: d80_ee and rms_tt^2 (e.g. uK_RJ^2). A_TT does not depend on lmax.
    """
    ell_rms = np.arange(2, ELL_MAX_RMS + 1, dtype=float)
    shape_rms = np.sum((2 * ell_rms + 1) * (ell_rms / ELL_PIVOT) ** alpha_tt) / (4 * np.pi)
    a_tt = rms_tt**2 / shape_rms
    c80 = 2 * np.pi * d80_ee / (ELL_PIVOT * (ELL_PIVOT + 1))
    ell = np.arange(lmax + 1, dtype=float)
    good = ell >= 2
    x = ell[good] / ELL_PIVOT
    cls = np.zeros((4, lmax + 1))
    cls[0, good] = a_tt * x**alpha_tt
    cls[1, good] = c80 * x**alpha_ee
    cls[2, good] = bb_over_ee * c80 * x**alpha_bb
    cls[3, good] = r_te * np.sqrt(cls[0, good] * cls[1, good])
    return cls


def _rj_per_cmb(freq_ghz: float) -> float:
    """dT_RJ / dT_CMB at a frequency (x^2 e^x / (e^x - 1)^2)."""
    import pysm3.units as u

    return (1.0 * u.uK_CMB).to_value(u.uK_RJ, equivalencies=u.cmb_equivalencies(freq_ghz * u.GHz))


def offline_template_spectra(component: str, lmax: int) -> np.ndarray:
    """(4, lmax + 1) spectra [uK_RJ^2] of the offline template fluctuations at the poles.

    Dust at 353 GHz (D_80^EE converted from uK_CMB^2), synchrotron at 23 GHz; constants
    and sources at the top of the module.
    """
    if component == "dust":
        return power_law_spectra(
            d80_ee=DUST_D80_EE_UK_CMB2 * _rj_per_cmb(DUST_FREQ_REF_GHZ) ** 2,
            alpha_ee=DUST_ALPHA_EE,
            alpha_bb=DUST_ALPHA_BB,
            alpha_tt=DUST_ALPHA_TT,
            bb_over_ee=DUST_BB_OVER_EE,
            rms_tt=INTENSITY_RMS_FRACTION * DUST_I_POLE_UK_RJ,
            r_te=DUST_R_TE,
            lmax=lmax,
        )
    if component == "synchrotron":
        return power_law_spectra(
            d80_ee=SYNC_D80_EE_UK_RJ2,
            alpha_ee=SYNC_ALPHA_EE,
            alpha_bb=SYNC_ALPHA_BB,
            alpha_tt=SYNC_ALPHA_TT,
            bb_over_ee=SYNC_BB_OVER_EE,
            rms_tt=INTENSITY_RMS_FRACTION * SYNC_I_POLE_UK_RJ,
            r_te=SYNC_R_TE,
            lmax=lmax,
        )
    raise ValueError(f"component = {component!r}: expected one of {COMPONENTS}")


@functools.lru_cache(maxsize=8)
def offline_templates(nside: int, master_seed: int) -> dict[str, np.ndarray]:
    """EMBEDDED OFFLINE templates (NOT pysm3 data): {"dust" at 353 GHz, "synchrotron" at 23 GHz}.

    Each is (3, npix) I Q U in uK_RJ, RING, Galactic:

        (dT, Q', U') = Gaussian field, spectra :func:`offline_template_spectra`,
                       lmax = 3 nside - 1, rng names ("foreground_template", component)
        I = e(b) max(I_pole + dT, f I_pole),   Q = e(b) Q',   U = e(b) U'

    with e(b) the latitude envelope (:func:`galactic_envelope`), I_pole the mean polar
    intensity and f = INTENSITY_FLOOR_FRACTION. Fixed across realisation seeds: depends
    only on (nside, master_seed). Arrays are read-only (cached).
    """
    nside = _check_nside(nside)
    lmax = 3 * nside - 1
    out = {}
    for component, i_pole, core in (
        ("dust", DUST_I_POLE_UK_RJ, DUST_PLANE_CORE_DEG),
        ("synchrotron", SYNC_I_POLE_UK_RJ, SYNC_PLANE_CORE_DEG),
    ):
        alm = gaussian_alm(
            offline_template_spectra(component, lmax),
            lmax,
            seeding.rng(master_seed, "foreground_template", component),
        )
        field_ = hp.alm2map(alm, nside, lmax=lmax, pixwin=False)
        envelope = galactic_envelope(nside, core)
        template = np.empty_like(field_)
        template[0] = envelope * np.maximum(i_pole + field_[0], INTENSITY_FLOOR_FRACTION * i_pole)
        template[1:] = envelope * field_[1:]
        template.flags.writeable = False
        out[component] = template
    return out


def _pysm_folder(pysm_local_data) -> str | None:
    """The pysm3 data folder: the argument, else $PYSM_LOCAL_DATA, else None (offline)."""
    if pysm_local_data is not None and str(pysm_local_data) != "":
        return str(pysm_local_data)
    env = os.environ.get("PYSM_LOCAL_DATA", "")
    return env or None


def _pysm_component_config(folder: str) -> dict[str, dict]:
    """The d0 and s0 preset configurations with their template files made absolute.

    Raises FileNotFoundError naming the first missing file (nothing is downloaded).
    """
    from pysm3.sky import PRESET_MODELS

    configs = {}
    for component, preset in PYSM_PRESETS.items():
        config = dict(PRESET_MODELS[preset])
        for key, value in config.items():
            if key.startswith("map_") and isinstance(value, str):
                path = Path(folder) / value
                if not path.is_file():
                    raise FileNotFoundError(
                        f"pysm3 template {path} (preset {preset} {key}, {component}) not found "
                        f"in pysm_local_data = {folder!r}: put the pysm3 data there (folder "
                        "holding pysm_2/) or leave pysm_local_data and $PYSM_LOCAL_DATA unset "
                        "for the embedded offline templates; nothing is downloaded"
                    )
                config[key] = str(path)
        configs[preset] = config
    return configs


def foreground_source(pysm_local_data=None) -> str:
    """Which foreground templates are used: :data:`PYSM_SOURCE` or :data:`OFFLINE_SOURCE`.

    pysm3 data are used if ``pysm_local_data`` (or $PYSM_LOCAL_DATA) is set; then all the
    d0/s0 template files must exist there (FileNotFoundError naming the missing one).
    """
    folder = _pysm_folder(pysm_local_data)
    if folder is None:
        return OFFLINE_SOURCE
    _pysm_component_config(folder)
    return PYSM_SOURCE


@dataclass(frozen=True, eq=False)
class ForegroundModels:
    """pysm3 models of the two components at one nside and where their templates come from."""

    source: str
    nside: int
    models: dict = field(repr=False)  # {"dust": pysm3 Model, "synchrotron": pysm3 Model}

    def template(self, component: str) -> np.ndarray:
        """(3, npix) reference template I Q U [uK_RJ] of a component (float64 copy)."""
        import pysm3.units as u

        model = self.models[component]
        return np.array(
            [np.asarray(model.I_ref.to_value(u.uK_RJ), dtype=float)]
            + [np.asarray(getattr(model, f"{s}_ref").to_value(u.uK_RJ), float) for s in "QU"]
        )


@functools.lru_cache(maxsize=4)
def _foreground_models(nside: int, master_seed: int | None, folder: str | None):
    import pysm3
    import pysm3.units as u

    if folder is not None:
        config = _pysm_component_config(folder)
        sky = pysm3.Sky(nside=nside, component_config=config, output_unit=MAP_UNIT)
        models = dict(zip(PYSM_PRESETS, sky.components))
        return ForegroundModels(source=PYSM_SOURCE, nside=nside, models=models)

    log.warning(
        "foregrounds: no pysm3 data (pysm_local_data / $PYSM_LOCAL_DATA unset); using %s",
        OFFLINE_SOURCE,
    )
    templates = offline_templates(nside, master_seed)

    def quantities(component):
        return [u.Quantity(templates[component][i], u.uK_RJ, copy=True) for i in range(3)]

    dust_i, dust_q, dust_u = quantities("dust")
    sync_i, sync_q, sync_u = quantities("synchrotron")
    models = {
        "dust": pysm3.models.ModifiedBlackBody(
            map_I=dust_i,
            map_Q=dust_q,
            map_U=dust_u,
            freq_ref_I=f"{DUST_FREQ_REF_GHZ} GHz",
            freq_ref_P=f"{DUST_FREQ_REF_GHZ} GHz",
            map_mbb_index=DUST_BETA,
            map_mbb_temperature=DUST_TEMPERATURE_K,
            unit_mbb_temperature="K",
            nside=nside,
        ),
        "synchrotron": pysm3.models.PowerLaw(
            map_I=sync_i,
            map_Q=sync_q,
            map_U=sync_u,
            freq_ref_I=f"{SYNC_FREQ_REF_GHZ} GHz",
            freq_ref_P=f"{SYNC_FREQ_REF_GHZ} GHz",
            map_pl_index=SYNC_BETA,
            nside=nside,
        ),
    }
    return ForegroundModels(source=OFFLINE_SOURCE, nside=nside, models=models)


def foreground_models(nside: int, master_seed: int, pysm_local_data=None) -> ForegroundModels:
    """pysm3 dust (d0-like) and synchrotron (s0-like) models at ``nside`` (cached).

    pysm3 data if available (see :func:`foreground_source`), else the offline templates
    of :func:`offline_templates` fed in memory to ``pysm3.models.ModifiedBlackBody``
    (353 GHz, beta_d, T_d) and ``pysm3.models.PowerLaw`` (23 GHz, beta_s).
    """
    nside = _check_nside(nside)
    folder = _pysm_folder(pysm_local_data)
    if folder is not None:
        folder = str(Path(folder).resolve())
        return _foreground_models(nside, None, folder)
    return _foreground_models(nside, int(master_seed), None)


def pysm_bandpass(bandpass: Bandpass, single_mode: bool = True):
    """(frequencies as a Quantity in GHz, pysm3 weights) of a band; samples at nu <= 0 dropped.

    pysm3 weights multiply I_nu; a single-mode detector of transmission w(nu) weighs
    I_nu by w(nu) c^2 / (2 nu^2), hence weights w / nu^2 (any constant factor drops out).
    """
    import pysm3.units as u

    freqs = np.asarray(bandpass.freqs_ghz, dtype=float)
    weights = np.asarray(bandpass.weights, dtype=float)
    keep = freqs > 0
    freqs, weights = freqs[keep], weights[keep]
    if freqs.size == 0 or np.trapezoid(weights, freqs) <= 0:
        raise ValueError("bandpass: expected positive frequencies and a positive integral")
    if single_mode:
        weights = weights / freqs**2
    return freqs * u.GHz, weights


def _unit_twin(model):
    """The same pysm3 model (class, reference frequencies, spectral parameters) on
    unit templates (12 pixels of 1 uK_RJ), for its band-integrated SED factors."""
    import pysm3
    import pysm3.units as u

    one = [np.ones(12) * u.uK_RJ for _ in range(3)]
    if type(model) is pysm3.models.ModifiedBlackBody:
        index, temperature = model.mbb_index, model.mbb_temperature.to(u.K)
        if np.ndim(index) or np.ndim(temperature):
            raise ValueError("ModifiedBlackBody with spatially varying beta / T: not d0-like")
        return pysm3.models.ModifiedBlackBody(
            map_I=one[0],
            map_Q=one[1],
            map_U=one[2],
            freq_ref_I=model.freq_ref_I,
            freq_ref_P=model.freq_ref_P,
            map_mbb_index=float(index.value),
            map_mbb_temperature=float(temperature.value),
            unit_mbb_temperature="K",
            nside=1,
        )
    if type(model) is pysm3.models.PowerLaw:
        if np.ndim(model.pl_index):
            raise ValueError("PowerLaw with a spatially varying index: not s0-like")
        return pysm3.models.PowerLaw(
            map_I=one[0],
            map_Q=one[1],
            map_U=one[2],
            freq_ref_I=model.freq_ref_I,
            freq_ref_P=model.freq_ref_P,
            map_pl_index=float(model.pl_index.value),
            nside=1,
        )
    raise TypeError(f"{type(model).__name__}: only ModifiedBlackBody and PowerLaw are supported")


def band_factors(model, bandpass: Bandpass, unit: str = MAP_UNIT, single_mode: bool = True):
    """(3,) band-integrated emission per uK_RJ of reference template, I Q U, in ``unit``.

    pysm3 evaluates the model's SED on unit templates with ``get_emission(freqs, weights)``
    [uK_RJ] and ``bandpass_unit_conversion(freqs, weights, unit)`` converts to ``unit``
    (factor in unit / uK_RJ; cut = 0 so both see the same samples).
    """
    import pysm3
    import pysm3.units as u

    freqs, weights = pysm_bandpass(bandpass, single_mode)
    emission = _unit_twin(model).get_emission(freqs, weights)[:, 0]
    factor = pysm3.bandpass_unit_conversion(freqs, weights, u.Unit(unit), cut=0.0)
    return np.asarray((emission * factor).to_value(u.Unit(unit)), dtype=float)


def _components(components) -> tuple[str, ...]:
    components = COMPONENTS if components is None else tuple(components)
    unknown = set(components) - set(COMPONENTS)
    if unknown:
        raise ValueError(f"components {sorted(unknown)}: expected a subset of {COMPONENTS}")
    return components


def foreground_emission(
    bandpass: Bandpass,
    nside: int,
    master_seed: int,
    pysm_local_data=None,
    unit: str = MAP_UNIT,
    components=None,
    single_mode: bool = True,
) -> np.ndarray:
    """Band-integrated foreground (3, npix) I Q U in ``unit`` (default K_CMB), unsmoothed.

    Sum over ``components`` (default dust and synchrotron) of template x band factor.
    """
    fg = foreground_models(nside, master_seed, pysm_local_data)
    total = np.zeros((N_STOKES, hp.nside2npix(fg.nside)))
    for component in _components(components):
        factors = band_factors(fg.models[component], bandpass, unit, single_mode)
        total += factors[:, None] * fg.template(component)
    return total


@functools.lru_cache(maxsize=4)
def _template_alms(fg: ForegroundModels, component: str) -> np.ndarray:
    """T E B a_lm of a template at lmax = 3 nside - 1 (healpy map2alm, 3 iterations)."""
    alm = hp.map2alm(fg.template(component), lmax=3 * fg.nside - 1, pol=True, iter=3)
    alm.flags.writeable = False
    return alm


def foreground_map(
    bandpass: Bandpass,
    nside: int,
    master_seed: int,
    fwhm_arcmin: float,
    pysm_local_data=None,
    lmax: int | None = None,
    components=None,
    single_mode: bool = True,
) -> np.ndarray:
    """Band-integrated foreground (3, npix) I Q U [K_CMB], smoothed with a Gaussian beam.

    K_CMB map = sum_c f_c(band) x template_c (see :func:`band_factors`), then the beam
    (:func:`smooth_alm`) is applied in harmonic space up to ``lmax`` (default
    3 nside - 1) without pixel window; ``fwhm_arcmin = 0`` returns the unsmoothed map.
    With constant spectral parameters I scales with f_I and (Q, U), hence (E, B), with
    f_P, so the template a_lm (cached) are scaled instead of the maps. The template
    source is given by :func:`foreground_source` (pysm3 data or offline templates).
    """
    fwhm_arcmin = _check_fwhm(fwhm_arcmin)
    if fwhm_arcmin == 0:
        return foreground_emission(
            bandpass, nside, master_seed, pysm_local_data, MAP_UNIT, components, single_mode
        )
    fg = foreground_models(nside, master_seed, pysm_local_data)
    lmax = 3 * fg.nside - 1 if lmax is None else int(lmax)
    if not 0 <= lmax <= 3 * fg.nside - 1:
        raise ValueError(f"lmax = {lmax}: expected 0 <= lmax <= 3 nside - 1 = {3 * fg.nside - 1}")
    alm = None
    for component in _components(components):
        factors = band_factors(fg.models[component], bandpass, MAP_UNIT, single_mode)
        scaled = _template_alms(fg, component) * factors[:, None]
        alm = scaled if alm is None else alm + scaled
    if alm is None:
        return np.zeros((N_STOKES, hp.nside2npix(fg.nside)))
    alm = np.array([hp.resize_alm(a, 3 * fg.nside - 1, 3 * fg.nside - 1, lmax, lmax) for a in alm])
    alm = smooth_alm(alm, fwhm_arcmin, lmax)
    return hp.alm2map(alm, fg.nside, lmax=lmax, pixwin=False)


# ========================================================================== channels
def channel_sky_map(
    channel,
    nside: int,
    lmax: int,
    r: float,
    master_seed: int,
    seed: int,
    pysm_local_data=None,
    single_mode: bool = True,
) -> dict:
    """The sky seen by a channel, RING, Galactic, (3, npix) I Q U in K_CMB.

    Returns {"cmb", "foreground", "total" = cmb + foreground} (each smoothed with the
    Gaussian beam of ``channel.fwhm_arcmin``, band limited at ``lmax``, no pixel window)
    and "foreground_source" (the flag of :func:`foreground_source`). The foreground is
    integrated over ``radiometry.channel_bandpass(channel)``; the CMB is realisation
    ``seed``, the same for every channel.
    """
    cmb = cmb_map(nside, lmax, r, master_seed, seed, channel.fwhm_arcmin)
    foreground = foreground_map(
        channel_bandpass(channel),
        nside,
        master_seed,
        channel.fwhm_arcmin,
        pysm_local_data,
        lmax=lmax,
        single_mode=single_mode,
    )
    return {
        "cmb": cmb,
        "foreground": foreground,
        "total": cmb + foreground,
        "foreground_source": foreground_source(pysm_local_data),
    }


# =============================================================================== I/O
def map_metadata(fwhm_arcmin: float | None = None, freq_ghz: float | None = None) -> dict:
    """What a CMB user reads first about a map: POLCCONV, and FWHM [arcmin] and FREQ [GHz]
    when known (FITS header keys; also the HDF5 attributes of the workflow's map files)."""
    metadata = {"POLCCONV": POLARISATION_CONVENTION}
    if fwhm_arcmin is not None:
        metadata["FWHM"] = float(fwhm_arcmin)
    if freq_ghz is not None:
        metadata["FREQ"] = float(freq_ghz)
    return metadata


def write_sky_map(
    path,
    maps: np.ndarray,
    extra_header: dict | None = None,
    foreground_source: str | None = None,
    fwhm_arcmin: float | None = None,
    freq_ghz: float | None = None,
) -> None:
    """Write (3, npix) I Q U [K_CMB] as a healpy FITS map, atomically.

    Header: COORDSYS = 'G', ORDERING = 'RING', TUNIT1..3 = 'K_CMB', POLCCONV = 'COSMO',
    FWHM [arcmin] and FREQ [GHz] (if given), FGSOURCE = the foreground flag (if given),
    plus ``extra_header`` (keys of at most 8 characters).
    """
    maps = np.asarray(maps, dtype=float)
    if maps.ndim != 2 or maps.shape[0] != N_STOKES or not hp.isnpixok(maps.shape[1]):
        raise ValueError(f"{path}: expected a (3, npix) I Q U map, got shape {maps.shape}")
    header = {**map_metadata(fwhm_arcmin, freq_ghz), **(extra_header or {})}
    if foreground_source is not None:
        header[FOREGROUND_SOURCE_KEY] = foreground_source
    for key in header:
        if len(str(key)) > 8:
            raise ValueError(f"{path}: FITS header key {key!r} longer than 8 characters")
    with atomic_path(path) as temporary:
        hp.write_map(
            str(temporary),
            maps,
            nest=False,
            coord="G",
            column_names=["I_STOKES", "Q_STOKES", "U_STOKES"],
            column_units=MAP_UNIT,
            extra_header=[(str(k).upper(), v) for k, v in header.items()],
            dtype=np.float64,
            overwrite=True,
        )


def read_sky_header(path) -> dict:
    """The header of the map extension of a sky map file, as a dict."""
    from astropy.io import fits

    with fits.open(path) as hdul:
        return dict(hdul[1].header)


def read_sky_map(path, nside: int | None = None) -> np.ndarray:
    """Read a (3, npix) I Q U map [K_CMB] written by :func:`write_sky_map` (RING), in the
    COSMO convention: a map whose header says POLCCONV = 'IAU' has its U negated (no
    POLCCONV: COSMO, healpy's default, is assumed).

    ValueError naming the file if it does not hold 3 fields of a valid HEALPix map, if
    POLCCONV is neither COSMO nor IAU, or (when ``nside`` is given) if its nside differs.
    """
    from astropy.io import fits

    try:
        with fits.open(path) as hdul:
            if len(hdul) < 2 or not isinstance(hdul[1], fits.BinTableHDU):
                raise ValueError(f"{path}: expected a HEALPix binary table in extension 1")
            n_fields = len(hdul[1].columns)
            convention = str(
                hdul[1].header.get("POLCCONV", hdul[0].header.get("POLCCONV", "COSMO"))
            )
    except OSError as error:
        raise ValueError(f"{path}: not a readable FITS file ({error})") from error
    if n_fields != N_STOKES:
        raise ValueError(f"{path}: expected 3 fields (I, Q, U), found {n_fields}")
    maps = np.asarray(hp.read_map(str(path), field=(0, 1, 2), dtype=np.float64))
    if maps.ndim != 2 or maps.shape[0] != N_STOKES or not hp.isnpixok(maps.shape[1]):
        raise ValueError(f"{path}: expected a (3, npix) HEALPix map, got shape {maps.shape}")
    found = hp.npix2nside(maps.shape[1])
    if nside is not None and found != int(nside):
        raise ValueError(f"{path}: expected nside = {nside}, found nside = {found}")
    convention = convention.strip().upper()
    if convention not in ("COSMO", "IAU"):
        raise ValueError(f"{path}: POLCCONV = {convention!r}, expected 'COSMO' or 'IAU'")
    if convention == "IAU":
        log.info("%s: IAU polarisation convention, U negated to COSMO", path)
        maps[2] = -maps[2]
    return maps
