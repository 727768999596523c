"""Spherical harmonic transforms of (I, Q, U) HEALPix maps in RING order, with ducc0.

The same transforms as healpy's ``alm2map(alm, nside, lmax, pixwin=False)`` and
``map2alm(maps, lmax, iter, pol=True, use_weights=False, use_pixel_weights=False)`` (T
with spin 0, E and B with spin 2, healpy's a_lm layout and polarisation convention; to
~1e-13, ``tests/sky/test_harmonics.py``), called on ducc0's SHT directly: on one thread at
nside 512, healpy 1.20's take 3.5 times (lmax 700) and 2.3 times (lmax 128) as long
(measured), and a map-domain seed transforms about ten maps.

    map2alm, iter = 0:  a_lm = (4 pi / npix) Y^dagger m        (quadrature, uniform weights)
    Jacobi iterations:  a_lm <- a_lm + map2alm_0(m - alm2map(a_lm))
"""

from __future__ import annotations

import functools

import ducc0
import healpy as hp
import numpy as np


@functools.lru_cache(maxsize=8)
def _geometry(nside: int) -> dict:
    """ducc0's ring description of a RING HEALPix map (theta, nphi, phi0, ringstart)."""
    return ducc0.healpix.Healpix_Base(nside, "RING").sht_info()


def _check_alm(alm: np.ndarray, lmax: int) -> None:
    if alm.ndim != 2 or alm.shape[0] != 3 or alm.shape[1] != hp.Alm.getsize(lmax):
        raise ValueError(
            f"a_lm of shape {alm.shape}: expected (3, {hp.Alm.getsize(lmax)}) T, E, B "
            f"up to lmax = {lmax}"
        )


def alm2map(alm: np.ndarray, nside: int, lmax: int, nthreads: int = 1) -> np.ndarray:
    """(3, npix) I, Q, U maps of T, E, B a_lm (3, nalm) up to ``lmax`` (no pixel window)."""
    alm = np.asarray(alm, dtype=np.complex128)
    _check_alm(alm, lmax)
    geometry = _geometry(int(nside))
    maps = np.empty((3, 12 * int(nside) ** 2))
    maps[:1] = ducc0.sht.synthesis(
        alm=alm[:1], lmax=lmax, spin=0, nthreads=nthreads, map=maps[:1], **geometry
    )
    maps[1:] = ducc0.sht.synthesis(
        alm=alm[1:], lmax=lmax, spin=2, nthreads=nthreads, map=maps[1:], **geometry
    )
    return maps


def map2alm(maps: np.ndarray, lmax: int, iter: int = 0, nthreads: int = 1) -> np.ndarray:
    """(3, nalm) T, E, B a_lm up to ``lmax`` of (3, npix) I, Q, U maps: the uniform-weight
    quadrature, then ``iter`` Jacobi iterations (as healpy's ``iter``)."""
    maps = np.asarray(maps, dtype=np.float64)
    if maps.ndim != 2 or maps.shape[0] != 3 or not hp.isnpixok(maps.shape[1]):
        raise ValueError(f"maps of shape {maps.shape}: expected (3, npix) I, Q, U HEALPix maps")
    nside = hp.npix2nside(maps.shape[1])
    alm = _quadrature(maps, nside, lmax, nthreads)
    for _ in range(iter):
        alm += _quadrature(maps - alm2map(alm, nside, lmax, nthreads), nside, lmax, nthreads)
    return alm


def _quadrature(maps: np.ndarray, nside: int, lmax: int, nthreads: int) -> np.ndarray:
    geometry = _geometry(int(nside))
    alm = np.empty((3, hp.Alm.getsize(lmax)), dtype=np.complex128)
    alm[:1] = ducc0.sht.adjoint_synthesis(
        map=maps[:1], lmax=lmax, spin=0, nthreads=nthreads, **geometry
    )
    alm[1:] = ducc0.sht.adjoint_synthesis(
        map=maps[1:], lmax=lmax, spin=2, nthreads=nthreads, **geometry
    )
    alm *= 4.0 * np.pi / maps.shape[1]
    return alm


# the accuracy asked of the band-limited sky's evaluation: far below the steps that
# nearest-pixel sampling leaves (~3 % of the sky's rms), at ~0.2-0.4 us per direction
BAND_LIMITED_EPSILON = 1e-7


class BandLimitedSky:
    """A sky given by its T, E, B a_lm up to ``lmax`` [K_CMB], evaluated at each sample's
    direction (litebird_sim's ``interpolate_alm``, ducc0's ``synthesis_general``) instead
    of at the nearest HEALPix pixel. A nearest-pixel TOD steps at every pixel crossing,
    and the steps have power at every frequency: times the 2 f_HWP HWPSS, their band near
    2 f_HWP lands at 0 and 4 f_HWP, where a demodulating map-maker reads the sky (at
    nside 32 the demodulated h x CMB is 40 times that of the band-limited sky, measured).
    A real TOD's sky band ends where the beam does."""

    def __init__(self, alm: np.ndarray, lmax: int, threads: int = 1):
        _check_alm(np.asarray(alm), lmax)
        import litebird_sim as lbs

        self.alm = np.asarray(alm)
        self.lmax = lmax
        self.threads = threads
        self.harmonics = lbs.SphericalHarmonics(
            np.ascontiguousarray(alm, dtype=np.complex128), lmax=lmax
        )

    @classmethod
    def from_map(cls, maps: np.ndarray, lmax: int | None = None, threads: int = 1):
        """The band-limited sky of (3, npix) I, Q, U maps: their a_lm up to ``lmax``
        (default 3 nside - 1), three Jacobi iterations."""
        nside = hp.npix2nside(np.shape(maps)[-1])
        lmax = 3 * nside - 1 if lmax is None else lmax
        return cls(map2alm(maps, lmax, iter=3, nthreads=threads), lmax, threads)

    def __add__(self, other: BandLimitedSky) -> BandLimitedSky:
        if other.lmax != self.lmax:
            raise ValueError(f"band-limited skies of lmax {self.lmax} and {other.lmax}")
        return BandLimitedSky(self.alm + other.alm, self.lmax, self.threads)

    def at(self, theta_phi_rad: np.ndarray) -> np.ndarray:
        """(3, n) I, Q, U [K_CMB] at (n, 2) directions (colatitude, longitude) [rad]."""
        from litebird_sim.maps_and_harmonics import interpolate_alm

        return np.asarray(
            interpolate_alm(
                self.harmonics,
                np.ascontiguousarray(theta_phi_rad, dtype=np.float64),
                epsilon=BAND_LIMITED_EPSILON,
                nthreads=self.threads,
            )
        )
