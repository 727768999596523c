"""EMBEDDED OFFLINE foreground templates (NOT pysm3 data), used when no pysm3 data folder
is given (flag :data:`~hwp_tes_systematics.sky.foregrounds.OFFLINE_SOURCE`).

Dust at 353 GHz and synchrotron at 23 GHz, (3, npix) I Q U in uK_RJ: Gaussian random
fields with power-law angular spectra (constants below, with their sources) times a
smooth Galactic-latitude envelope, fixed for a master seed and nside. pysm3 models scale
them in frequency (:mod:`~hwp_tes_systematics.sky.foregrounds`).
"""

from __future__ import annotations

import functools

import healpy as hp
import numpy as np

from .. import seeding
from .cmb import _check_nside, gaussian_alm

COMPONENTS = ("dust", "synchrotron")  # keys of the templates and of the foreground models
DUST_FREQ_REF_GHZ = 353.0  # offline dust template frequency (I, Q, U)
SYNC_FREQ_REF_GHZ = 23.0  # offline synchrotron template frequency (I, Q, U), WMAP K band

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
