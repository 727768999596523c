"""Spherical harmonic transforms of (I, Q, U) HEALPix maps in RING order, with ducc0.

The same transforms as healpy's ``alm2map(alm, nside, lmax, pixwin=False)`` and
``map2alm(maps, lmax, iter, pol=True, use_weights=False, use_pixel_weights=False)`` (T
with spin 0, E and B with spin 2, healpy's a_lm layout and polarisation convention; to
~1e-13, ``tests/test_harmonics.py``), called on ducc0's SHT directly: on one thread at
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
