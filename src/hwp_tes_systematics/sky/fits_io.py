"""FITS I/O of sky maps: healpy FITS files, RING, Galactic (COORDSYS = 'G'), K_CMB.

Maps are written atomically (:func:`hwp_tes_systematics.io.atomic_path`) with POLCCONV =
'COSMO', FWHM / FREQ when known, and the foreground flag under
:data:`FOREGROUND_SOURCE_KEY`; maps read in the IAU convention are converted to COSMO.
"""

from __future__ import annotations

import logging

import healpy as hp
import numpy as np

from ..io import atomic_path
from .conventions import MAP_UNIT, N_STOKES, POLARISATION_CONVENTION

log = logging.getLogger(__package__)  # "hwp_tes_systematics.sky", as before the split

FOREGROUND_SOURCE_KEY = "FGSOURCE"  # FITS header key of the foreground flag


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
