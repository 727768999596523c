"""sky.harmonics: ducc0's transforms give healpy's, to round-off."""

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.sky import harmonics

NSIDE, LMAX = 32, 64


def random_alm(lmax, seed=1):
    rng = np.random.default_rng(seed)
    size = hp.Alm.getsize(lmax)
    alm = rng.standard_normal((3, size)) + 1j * rng.standard_normal((3, size))
    alm[:, : lmax + 1] = alm[:, : lmax + 1].real  # m = 0 real
    alm[1:, :2] = 0.0  # no E, B at ell < 2
    return alm


def test_alm2map_is_healpys():
    alm = random_alm(LMAX)
    expected = hp.alm2map(alm, NSIDE, lmax=LMAX, pixwin=False)
    produced = harmonics.alm2map(alm, NSIDE, LMAX)
    np.testing.assert_allclose(produced, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("iterations", [0, 1, 3])
def test_map2alm_is_healpys_with_its_iterations(iterations):
    maps = hp.alm2map(random_alm(3 * NSIDE - 1, 2), NSIDE, pixwin=False)
    maps[1:, :100] = 0.0  # a masked corner: the iterations matter
    expected = hp.map2alm(
        maps, lmax=LMAX, iter=iterations, pol=True, use_weights=False, use_pixel_weights=False
    )
    produced = harmonics.map2alm(maps, LMAX, iter=iterations)
    np.testing.assert_allclose(produced, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_wrong_shapes_are_refused():
    with pytest.raises(ValueError, match="expected \\(3, "):
        harmonics.alm2map(random_alm(LMAX)[:, :-1], NSIDE, LMAX)
    with pytest.raises(ValueError, match="HEALPix maps"):
        harmonics.map2alm(np.zeros((3, 100)), LMAX)


def test_a_band_limited_sky_at_pixel_centres_is_its_map():
    """BandLimitedSky.at evaluates the a_lm sum at any direction: at the pixel centres it
    is alm2map (to the 1e-7 accuracy asked of ducc0's synthesis_general)."""
    alm = random_alm(3 * NSIDE - 1, 3)
    sky = harmonics.BandLimitedSky(alm, 3 * NSIDE - 1)
    theta, phi = hp.pix2ang(NSIDE, np.arange(hp.nside2npix(NSIDE)))
    expected = harmonics.alm2map(alm, NSIDE, 3 * NSIDE - 1)
    produced = sky.at(np.stack([theta, phi], axis=1))
    np.testing.assert_allclose(produced, expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    both = sky + harmonics.BandLimitedSky(2 * alm, 3 * NSIDE - 1)
    np.testing.assert_allclose(both.alm, 3 * alm)
    with pytest.raises(ValueError, match="expected \\(3, "):
        harmonics.BandLimitedSky(alm[:, :10], 3 * NSIDE - 1)
