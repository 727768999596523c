"""Masks, f_sky weights, pseudo spectra with w2 correction, binning."""

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.analysis import hilc, spectra


def latitude_deg(nside):
    return hp.pix2ang(nside, np.arange(hp.nside2npix(nside)), lonlat=True)[1]


# ---------------------------------------------------------------------------- masks
def test_galactic_mask_keeps_high_latitudes():
    nside = 32
    mask = spectra.galactic_mask(nside, 20.0)
    b = latitude_deg(nside)
    np.testing.assert_array_equal(mask, np.abs(b) >= 20.0)
    assert abs(mask.mean() - (1 - np.sin(np.radians(20.0)))) < 0.01
    assert spectra.galactic_mask(nside, 0.0).all()
    with pytest.raises(ValueError):
        spectra.galactic_mask(nside, -5.0)


def test_common_mask_excludes_unseen_in_any_map_and_galactic_plane():
    nside = 16
    npix = hp.nside2npix(nside)
    b = latitude_deg(nside)
    rng = np.random.default_rng(0)
    maps = [rng.standard_normal((3, npix)) for _ in range(3)]
    high = np.flatnonzero(np.abs(b) > 40)
    maps[0][1, high[:5]] = hp.UNSEEN  # Q only, map 0
    maps[2][0, high[5:12]] = hp.UNSEEN  # I only, map 2
    maps[1][2, high[12]] = np.nan
    mask = spectra.common_mask(maps, 30.0)
    expected = np.abs(b) >= 30.0 - 1e-9  # a ring of pixel centres lies at |b| = 30 deg
    expected[high[:13]] = False
    np.testing.assert_array_equal(mask, expected)
    with pytest.raises(ValueError):
        spectra.common_mask([maps[0], maps[1][:, :100]], 30.0)


@pytest.mark.parametrize("method", ["rescaled", "product"])
def test_apodized_mask_zero_outside_and_one_far_from_edges(method):
    nside, cut, apod = 64, 20.0, 6.0
    binary = spectra.galactic_mask(nside, cut)
    mask = spectra.apodized_mask(binary, apod, method=method)
    b = np.abs(latitude_deg(nside))
    assert np.all(mask[~binary] == 0)
    assert np.all((mask >= 0) & (mask <= 1))
    far = b > cut + 2.5 * apod
    assert np.all(mask[far] > 0.99)
    near = binary & (b < cut + 0.5)
    if method == "rescaled":  # continuous at the edge: small values next to it
        assert np.all(mask[near] < 0.25)
    else:  # the product leaves a step of ~0.5 at the edge
        assert np.all(np.abs(mask[near] - 0.5) < 0.15)
    # monotonic increase away from the edge (along the pixel centres' latitude)
    kept = np.flatnonzero(binary & (b < cut + 3 * apod))
    order = kept[np.argsort(b[kept])]
    profile = np.convolve(mask[order], np.ones(50) / 50, mode="valid")
    assert np.all(np.diff(profile) > -1e-3)
    np.testing.assert_array_equal(spectra.apodized_mask(binary, 0.0), binary.astype(float))
    with pytest.raises(ValueError):
        spectra.apodized_mask(binary, 5.0, method="cosine")


def test_fsky_weights():
    nside = 16
    binary = spectra.galactic_mask(nside, 30.0)
    w = spectra.fsky_weights(binary)
    assert w["fsky"] == pytest.approx(binary.mean())
    assert w["w2"] == w["w4"] == pytest.approx(binary.mean())
    assert w["fsky_eff"] == pytest.approx(binary.mean())
    half = np.full(hp.nside2npix(nside), 0.5)
    w = spectra.fsky_weights(half)
    assert (w["fsky"], w["w2"], w["w4"], w["fsky_eff"]) == pytest.approx((0.5, 0.25, 0.0625, 1))


# -------------------------------------------------------------------------- spectra
def test_pseudo_spectra_full_sky_reproduce_alm2cl():
    lmax = 40
    rng = np.random.default_rng(1)
    nalm = hp.Alm.getsize(lmax)
    m = hp.Alm.getlm(lmax)[1]
    z = rng.standard_normal((3, nalm)) + 1j * rng.standard_normal((3, nalm))
    z[:, m == 0] = z[:, m == 0].real
    alm = np.array([z[0], 0.6 * z[0] + z[1], 0.3 * z[2] + 0.2 * z[1]])  # TE, EB != 0
    cl = spectra.pseudo_spectra(alm, lmax, 1.0)
    assert cl.shape == (6, lmax + 1)
    np.testing.assert_allclose(cl, hp.alm2cl(alm), rtol=1e-14, atol=0)
    np.testing.assert_allclose(spectra.pseudo_spectra(alm, lmax, 0.25), 4 * cl, rtol=1e-14)
    cross = spectra.pseudo_spectra(alm, lmax, 1.0, alm2=2 * alm)
    np.testing.assert_allclose(cross, 2 * cl, rtol=1e-14)
    with pytest.raises(ValueError):
        spectra.pseudo_spectra(alm, lmax + 1, 1.0)
    with pytest.raises(ValueError):
        spectra.pseudo_spectra(alm, lmax, 0.0)


def test_white_noise_spectrum_recovered_on_partial_sky():
    nside, lmax = 64, 128
    npix = hp.nside2npix(nside)
    sigma = 3e-6  # K per pixel
    rng = np.random.default_rng(11)
    maps = sigma * rng.standard_normal((3, npix))
    maps[:, :2000] = hp.UNSEEN  # an unobserved cap
    binary = spectra.common_mask([maps], 20.0)
    mask = spectra.apodized_mask(binary, 5.0)
    w = spectra.fsky_weights(mask)
    assert 0.3 < w["w2"] < 0.6
    alm = hilc.maps_to_alm(maps, mask, lmax)
    cl = spectra.pseudo_spectra(alm, lmax, w["w2"])
    expected = sigma**2 * 4 * np.pi / npix  # white noise C_ell = sigma^2 Omega_pix
    # one wide bin (about 16500 modes, 6000 effective: 1.8 % scatter), then three bins
    _, wide = spectra.binned_spectrum(cl, [(10, lmax + 1)])
    np.testing.assert_allclose(wide[:3, 0] / expected, 1.0, atol=0.05)  # TT, EE, BB
    assert np.all(np.abs(wide[3:, 0]) < 0.02 * expected)  # TE, EB, TB: no correlation
    bins = hilc.multipole_bins(10, lmax, 40)
    _, binned = spectra.binned_spectrum(cl, bins)
    np.testing.assert_allclose(binned[:3] / expected, 1.0, atol=0.1)
    # without the w2 correction the spectrum is low by the factor w2
    assert np.all(binned[:3] * w["w2"] / expected < 0.7)


def test_binned_spectrum_weights_and_centres():
    cl = np.arange(11.0)
    bins = [(2, 5), (5, 11)]
    centres, binned = spectra.binned_spectrum(cl, bins)
    for (lo, hi), value, centre in zip(bins, binned, centres):
        ell = np.arange(lo, hi)
        assert value == pytest.approx(np.sum((2 * ell + 1) * ell) / np.sum(2 * ell + 1))
        assert centre == pytest.approx(value)  # C_ell = ell: the weighted mean ell
    _, flat = spectra.binned_spectrum(np.full((6, 11), 2.5), bins)
    assert flat.shape == (6, 2)
    np.testing.assert_allclose(flat, 2.5)
    with pytest.raises(ValueError):
        spectra.binned_spectrum(cl, [(2, 12)])


# -------------------------------------------------------- one analysis resolution
def test_common_mask_region_on_a_coarser_grid():
    """region_nside decides the region on a coarser grid: a coarse pixel is kept whole or
    dropped whole, by its centre's latitude and by every fine pixel inside it."""
    nside, region = 32, 8
    maps = [np.zeros((3, hp.nside2npix(nside)))]
    coarse = spectra.galactic_mask(region, 30.0)
    expected = hp.ud_grade(coarse.astype(float), nside) == 1.0
    np.testing.assert_array_equal(spectra.common_mask(maps, 30.0, region_nside=region), expected)
    # one unobserved fine pixel drops its coarse parent: (nside / region)^2 fine pixels
    kept = np.flatnonzero(expected)
    maps[0][1, kept[0]] = hp.UNSEEN
    mask = spectra.common_mask(maps, 30.0, region_nside=region)
    assert expected.sum() - mask.sum() == (nside // region) ** 2
    parent = hp.ang2pix(region, *hp.pix2ang(nside, kept[0]))
    children = hp.ang2pix(region, *hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))) == parent
    assert not mask[children].any()
    # the fine grid's own cut follows the fine pixel centres: another region
    assert spectra.common_mask(maps, 30.0).sum() != mask.sum()
    with pytest.raises(ValueError, match="region_nside = 64"):
        spectra.common_mask(maps, 30.0, region_nside=64)


def test_one_analysis_mask_at_every_map_resolution_gives_one_spectrum():
    """Maps of one band-limited sky made at nside 32 and 64, analysed on the nside-16
    region at one lmax and beam: the masks cover the same region (f_sky within 0.2 %) and
    the BB pseudo-spectra agree to 1 % at ell 4-40 (the pixel windows are not applied:
    the maps are alm2map of the same a_lm). Each on its own grid's region: 0.8 % and 2.8 %."""
    from hwp_tes_systematics.analysis import channel_alms

    lmax = 40
    ell = np.arange(lmax + 1)
    cl = np.zeros((4, lmax + 1))
    cl[:3, 2:] = 1.0 / ell[2:] ** 2
    np.random.seed(1)  # hp.synalm draws from numpy's global generator
    alm = hp.synalm(cl, lmax=lmax, new=True)
    settings = {"galactic_cut_deg": 20.0, "mask_apodization_deg": 10.0, "analysis_nside": 16}
    harmonic = channel_alms.HarmonicSettings(lmax=lmax, common_fwhm_arcmin=60.0, map2alm_iter=3)
    spectra_bb, f_sky = [], []
    for nside in (32, 64):
        maps = hp.alm2map(alm, nside, lmax=lmax)
        mask = channel_alms.analysis_mask([np.ones(hp.nside2npix(nside), bool)], settings)
        f_sky.append(mask.mean())
        spectra_bb.append(hp.alm2cl(harmonic.alm(maps, 60.0, mask))[2])
    assert abs(f_sky[1] / f_sky[0] - 1) < 2e-3
    np.testing.assert_allclose(spectra_bb[1][4:], spectra_bb[0][4:], rtol=0.01)
