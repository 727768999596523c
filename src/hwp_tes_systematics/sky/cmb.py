"""CMB realisations from the PTEP spectra, and the Gaussian a_lm / beam tools of the package.

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

:func:`gaussian_alm`, :func:`smooth_alm` (Gaussian beam) and the nside / FWHM checks
are also used by the offline foreground templates and the foreground maps.
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import healpy as hp
import numpy as np

from .. import seeding
from .conventions import N_STOKES

CMB_SCALAR_FILE = "Cls_Planck2018_for_PTEP_2020_r0.fits"  # scalar + lensing, r = 0
CMB_TENSOR_FILE = "Cls_Planck2018_for_PTEP_2020_tensor_r1.fits"  # tensor only, r = 1
UK2_TO_K2 = 1e-12  # the files are in uK_CMB^2
SPECTRA_ORDER = ("TT", "EE", "BB", "TE")


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


BEAM_POWER_FLOOR = 1e-10  # B_ell^2 below which a beamed map's multipoles are dropped


def beam_band_limit(fwhm_arcmin: float, lmax: int, power_floor: float = BEAM_POWER_FLOOR) -> int:
    """The band a map smoothed by the beam needs: the smallest L <= ``lmax`` with
    B_ell^2 < ``power_floor`` for every ell > L (T, E and B windows), i.e.
    L (L + 1) sigma^2 ~ -ln(power_floor); ``lmax`` for no beam or a beam too narrow.

    A 70.5' beam (L1-040): L = 551; 30.8' (M1-140): 1261; above it the beam has removed all
    but 1e-10 of the power, so a map synthesised up to L equals the full-band one to
    < 1e-4 of its rms in every pixel (``tests/simulation/test_map_domain.py``), at (L / lmax)^2 of the cost.
    """
    fwhm_arcmin = _check_fwhm(fwhm_arcmin)
    if fwhm_arcmin == 0:
        return lmax
    beam = hp.gauss_beam(np.radians(fwhm_arcmin / 60.0), lmax=lmax, pol=True)[:, :3]
    above = np.nonzero(np.max(beam**2, axis=1) >= power_floor)[0]
    return int(min(lmax, above.max() + 1)) if above.size else 0


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


def transfer_cmb_alm(lmax: int, r: float, master_seed: int, fwhm_arcmin: float) -> np.ndarray:
    """The fixed pass's reference CMB a_lm (3, nalm) [K_CMB], beam-smoothed: its own
    random stream ("cmb-transfer"), so it is none of the seeds' realizations."""
    cls = cmb_spectra(r, lmax)
    alm = gaussian_alm(cls, lmax, seeding.rng(master_seed, "cmb-transfer"))
    return smooth_alm(alm, fwhm_arcmin, lmax)


def seed_cmb_alm(lmax: int, r: float, master_seed: int, seed: int, fwhm_arcmin: float):
    """CMB realization ``seed`` (3, nalm) [K_CMB], beam-smoothed: the same draw as the full
    path's :func:`sky.cmb.cmb_map` for that seed."""
    return smooth_alm(cmb_alm(lmax, r, master_seed, seed), fwhm_arcmin, lmax)


def band_limited_seed_cmb(lmax: int, r: float, master_seed: int, seed: int, fwhm_arcmin: float):
    """(a_lm, L): CMB realization ``seed`` as :func:`seed_cmb_alm` (the same draw), cut
    at the beam's band limit L = :func:`sky.beam_band_limit` (B_ell^2 >= 1e-10): its maps
    equal the full band's to < 1e-4 of their rms, at (L / lmax)^2 of the transforms."""
    alm = seed_cmb_alm(lmax, r, master_seed, seed, fwhm_arcmin)
    band = beam_band_limit(fwhm_arcmin, lmax)
    return hp.resize_alm(alm, lmax, lmax, band, band), band


def tensor_b_alm(lmax: int, master_seed: int, seed: int, fwhm_arcmin: float) -> np.ndarray:
    """(3, nalm) [K_CMB] B modes alone of a primordial tensor sky at r = 1
    (:func:`tensor_bb_r1`), beam-smoothed: seed ``seed``'s probe of the map's response to
    r, stream ("cmb tensor b", seed), independent of the seed's CMB."""
    cls = np.zeros((4, int(lmax) + 1))
    cls[2] = tensor_bb_r1(lmax)
    alm = gaussian_alm(cls, lmax, seeding.rng(master_seed, "cmb tensor b", int(seed)))
    return smooth_alm(alm, fwhm_arcmin, lmax)


def tensor_excess_unit_alm(lmax: int, master_seed: int, seed: int) -> np.ndarray:
    """(nalm,) a B-mode a_lm of unit power, ell = 2..lmax: the field a map-domain seed
    scales into the filters' excess BB of its tensor probe's B modes, stream ("tensor
    filter excess", seed), the same for every channel."""
    return _unit_b_alm(lmax, seeding.rng(master_seed, "tensor filter excess", seed))


def filter_excess_unit_alms(lmax: int, master_seed: int, seed: int) -> np.ndarray:
    """(2, nalm) B-mode a_lm of unit power, ell = 2..lmax, of seed ``seed``: the fields a
    map-domain seed scales into the filters' excess BB by origin (B modes, T and E modes;
    :func:`simulation.filter_response.excess_bb_alms`). Streams ("cmb filter excess",
    seed, origin), the same for every channel; ordered by ell as :func:`gaussian_alm`."""
    return np.array(
        [
            _unit_b_alm(lmax, seeding.rng(master_seed, "cmb filter excess", seed, row))
            for row in range(2)
        ]
    )


def _unit_b_alm(lmax: int, rng) -> np.ndarray:
    """(nalm,) a B-mode a_lm of unit power at ell = 2..lmax from ``rng`` (the order of
    :func:`gaussian_alm`)."""
    unit = np.zeros((4, lmax + 1))
    unit[2, 2:] = 1.0
    return gaussian_alm(unit, lmax, rng)[2]
