"""Input sky: PTEP CMB spectra, Gaussian a_lm, CMB maps, d0s0-like foregrounds, FITS I/O."""

import logging

import healpy as hp
import numpy as np
import pytest
from scipy.constants import c as C_LIGHT
from scipy.constants import h as H_PLANCK
from scipy.constants import k as K_BOLTZMANN

from hwp_tes_systematics import seeding, sky
from hwp_tes_systematics.instrument.channels import Channel
from hwp_tes_systematics.instrument.radiometry import top_hat_bandpass

T_CMB_ASTROPY_K = 2.7255  # the T_CMB of pysm3's (astropy's) K_CMB equivalencies
MASTER = 20240601


@pytest.fixture(autouse=True)
def _no_pysm_env(monkeypatch):
    """The offline templates unless a test asks for pysm3 data."""
    monkeypatch.delenv("PYSM_LOCAL_DATA", raising=False)


def make_channel(name, center_ghz, width_ghz, fwhm_arcmin):
    return Channel(
        name=name,
        telescope="MFT",
        bandcenter_ghz=center_ghz,
        bandwidth_ghz=width_ghz,
        band_freqs_ghz=np.array([center_ghz]),
        band_weights=np.array([1.0]),  # 0/1 weights: rebuilt as an exact top-hat
        net_detector_ukrts=30.0,
        fknee_mhz=20.0,
        fmin_hz=1e-5,
        alpha=1.0,
        fwhm_arcmin=fwhm_arcmin,
        sampling_rate_hz=19.0,
        hwp_rpm=39.0,
        number_of_detectors=2,
        detectors=("a", "b"),
    )


def d_ell(cl):
    ell = np.arange(cl.shape[-1])
    return ell * (ell + 1) * cl / (2 * np.pi)


def rj_per_cmb(freq_ghz):
    """dT_RJ / dT_CMB = x^2 e^x / (e^x - 1)^2, x = h nu / k T_CMB."""
    x = H_PLANCK * np.asarray(freq_ghz) * 1e9 / (K_BOLTZMANN * T_CMB_ASTROPY_K)
    return x**2 * np.exp(x) / np.expm1(x) ** 2


def mbb_rj(freq_ghz, ref_ghz, beta=sky.DUST_BETA, temperature_k=sky.DUST_TEMPERATURE_K):
    """T_RJ(nu) / T_RJ(nu_0) of a modified black body."""

    def planck(nu_ghz):
        nu = np.asarray(nu_ghz) * 1e9
        return (
            2
            * H_PLANCK
            * nu**3
            / C_LIGHT**2
            / np.expm1(H_PLANCK * nu / (K_BOLTZMANN * temperature_k))
        )

    return (np.asarray(freq_ghz) / ref_ghz) ** (beta - 2) * planck(freq_ghz) / planck(ref_ghz)


# ------------------------------------------------------------------------ spectra
def test_cmb_spectra_units_and_content():
    cls = sky.cmb_spectra(0.0, 1500)
    assert cls.shape == (4, 1501)
    uk2 = 1e12
    assert 5000 < d_ell(cls[0])[220] * uk2 < 6500  # first acoustic peak, K^2 -> uK^2
    lens = sky.lensing_bb(1500)
    np.testing.assert_array_equal(cls[2], lens)
    assert 1e-18 < lens[80] < 3e-18  # C_80^BB, lensing, K^2
    assert 0.05 < d_ell(lens)[1000] * uk2 < 0.15  # D_1000^BB ~ 0.1 uK^2
    tensor = sky.tensor_bb_r1(1500)
    d_tensor = d_ell(tensor) * uk2
    assert 0.03 < d_tensor[80] < 0.1  # r = 1: D_80^BB ~ 0.065 uK^2
    assert 60 <= 30 + np.argmax(d_tensor[30:300]) <= 120  # recombination bump
    assert tensor[1000] < 0.05 * lens[1000]  # no lensing in the tensor file


def test_cmb_spectra_is_lensing_plus_r_tensor():
    r = 0.01
    cls = sky.cmb_spectra(r, 600)
    np.testing.assert_array_equal(cls[2], sky.lensing_bb(600) + r * sky.tensor_bb_r1(600))
    tt_tensor = sky.cmb_spectra(1.0, 600)[0] - sky.cmb_spectra(0.0, 600)[0]
    assert tt_tensor[2] > 0  # TT, EE, TE tensor parts are included too
    with pytest.raises(ValueError, match="r = -0.1"):
        sky.cmb_spectra(-0.1, 100)
    with pytest.raises(ValueError, match="lmax = 5000"):
        sky.cmb_spectra(0.0, 5000)


# ----------------------------------------------------------------- gaussian_alm
def _binned_chi2(hat, expected, variance, lmin=2, width=16):
    """chi^2 of binned (hat - expected) with per-ell variances; also the largest |z|."""
    chi2, zmax, nbins = 0.0, 0.0, 0
    for start in range(lmin, hat.size - width + 1, width):
        sl = slice(start, start + width)
        z = np.sum(hat[sl] - expected[sl]) / np.sqrt(np.sum(variance[sl]))
        chi2 += z**2
        zmax = max(zmax, abs(z))
        nbins += 1
    return chi2, zmax, nbins


def test_gaussian_alm_reproduces_spectra_within_cosmic_variance():
    lmax = 256
    cls = sky.cmb_spectra(0.05, lmax)
    alm = sky.gaussian_alm(cls, lmax, np.random.default_rng(11))
    assert alm.shape == (3, hp.Alm.getsize(lmax))
    hat = hp.alm2cl(alm)  # TT EE BB TE EB TB
    nmodes = 2 * np.arange(lmax + 1) + 1.0
    tt, ee, bb, te = cls
    checks = {
        "TT": (hat[0], tt, 2 * tt**2 / nmodes),
        "EE": (hat[1], ee, 2 * ee**2 / nmodes),
        "BB": (hat[2], bb, 2 * bb**2 / nmodes),
        "TE": (hat[3], te, (te**2 + tt * ee) / nmodes),
        "EB": (hat[4], 0 * ee, ee * bb / nmodes),
        "TB": (hat[5], 0 * tt, tt * bb / nmodes),
    }
    for name, (h, expected, variance) in checks.items():
        chi2, zmax, nbins = _binned_chi2(h, expected, variance)
        assert chi2 < nbins + 5 * np.sqrt(2 * nbins), (name, chi2, nbins)
        assert zmax < 5, (name, zmax)
    # the TE correlation is really there: its binned estimate is far from zero
    chi2_null, _, _ = _binned_chi2(hat[3], 0 * te, (te**2 + tt * ee) / nmodes)
    assert chi2_null > 10 * 15
    # m = 0 modes are real
    m0 = hp.Alm.getidx(lmax, np.arange(lmax + 1), 0)
    assert np.all(alm[:, m0].imag == 0)


def test_gaussian_alm_deterministic_and_nested_in_lmax():
    cls = sky.cmb_spectra(0.0, 128)
    a = sky.gaussian_alm(cls, 128, np.random.default_rng(5))
    b = sky.gaussian_alm(cls, 128, np.random.default_rng(5))
    c = sky.gaussian_alm(cls, 128, np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    low = sky.gaussian_alm(cls, 64, np.random.default_rng(5))
    ell, m = hp.Alm.getlm(64)
    np.testing.assert_array_equal(low, a[:, hp.Alm.getidx(128, ell, m)])
    with pytest.raises(ValueError, match="expected"):
        sky.gaussian_alm(cls[:3], 128, np.random.default_rng(5))


# -------------------------------------------------------------------- CMB maps
@pytest.mark.slow
def test_cmb_map_seeds_and_channel_independence():
    nside, lmax = 16, 47
    first = sky.cmb_map(nside, lmax, 0.0, MASTER, 3)
    assert first.shape == (3, hp.nside2npix(nside))
    np.testing.assert_array_equal(first, sky.cmb_map(nside, lmax, 0.0, MASTER, 3))
    assert not np.allclose(first, sky.cmb_map(nside, lmax, 0.0, MASTER, 4))
    assert not np.allclose(first, sky.cmb_map(nside, lmax, 0.0, MASTER + 1, 3))
    # the stream is rng(master_seed, "cmb", seed), whatever the channel
    np.testing.assert_array_equal(
        sky.cmb_alm(lmax, 0.0, MASTER, 3),
        sky.gaussian_alm(sky.cmb_spectra(0.0, lmax), lmax, seeding.rng(MASTER, "cmb", 3)),
    )
    # K_CMB: CMB temperature rms of order 100 uK
    assert 3e-5 < np.std(first[0]) < 3e-4
    # the map is the a_lm of cmb_alm, beam-smoothed, without pixel window
    expected = hp.alm2map(
        sky.smooth_alm(sky.cmb_alm(lmax, 0.0, MASTER, 3), 120.0, lmax), nside, lmax=lmax
    )
    np.testing.assert_allclose(sky.cmb_map(nside, lmax, 0.0, MASTER, 3, 120.0), expected)
    # the same CMB for every channel: only the beam differs
    a = make_channel("A-100", 100.0, 23.0, 120.0)
    b = make_channel("B-280", 280.0, 28.0, 120.0)
    c = make_channel("C-140", 140.0, 42.0, 200.0)
    maps = {ch.name: sky.channel_sky_map(ch, nside, lmax, 0.0, MASTER, 3) for ch in (a, b, c)}
    np.testing.assert_array_equal(maps["A-100"]["cmb"], maps["B-280"]["cmb"])
    np.testing.assert_allclose(maps["A-100"]["cmb"], expected)
    np.testing.assert_allclose(
        maps["C-140"]["cmb"], sky.cmb_map(nside, lmax, 0.0, MASTER, 3, 200.0)
    )
    assert not np.allclose(maps["A-100"]["foreground"], maps["B-280"]["foreground"])
    for m in maps.values():
        np.testing.assert_array_equal(m["total"], m["cmb"] + m["foreground"])
        assert m["foreground_source"] == sky.OFFLINE_SOURCE
    with pytest.raises(ValueError, match="fwhm_arcmin"):
        sky.cmb_map(nside, lmax, 0.0, MASTER, 3, -1.0)


# ------------------------------------------------------------------ foregrounds
@pytest.mark.slow
def test_offline_dust_follows_mbb_in_k_cmb():
    nside = 8
    dust = {
        nu: sky.foreground_emission(top_hat_bandpass(nu, 0.2), nside, MASTER, components=["dust"])
        for nu in (100.0, 353.0)
    }
    template = sky.offline_templates(nside, MASTER)["dust"]
    # at the reference frequency: the template converted from uK_RJ to K_CMB
    np.testing.assert_allclose(dust[353.0], template * 1e-6 / rj_per_cmb(353.0), rtol=1e-4)
    ratio = mbb_rj(100.0, 353.0) * rj_per_cmb(353.0) / rj_per_cmb(100.0)
    np.testing.assert_allclose(dust[100.0], ratio * dust[353.0], rtol=1e-3)
    p100, p353 = (np.hypot(dust[nu][1], dust[nu][2]) for nu in (100.0, 353.0))
    assert np.all(p353 > 10 * p100)


@pytest.mark.slow
def test_offline_synchrotron_is_power_law_in_rj():
    nside = 8
    sync = {
        nu: sky.foreground_emission(
            top_hat_bandpass(nu, 0.1), nside, MASTER, unit="uK_RJ", components=["synchrotron"]
        )
        for nu in (23.0, 30.0, 60.0)
    }
    np.testing.assert_allclose(
        sync[23.0], sky.offline_templates(nside, MASTER)["synchrotron"], rtol=1e-5
    )
    np.testing.assert_allclose(sync[60.0], 2.0**sky.SYNC_BETA * sync[30.0], rtol=1e-4)


def test_wide_band_integration_single_mode_convention():
    """K_CMB = integral w T_RJ / integral w dT_RJ/dT_CMB (single mode); pysm3's own weights differ."""
    band = top_hat_bandpass(100.0, 23.0)
    model = sky.foreground_models(8, MASTER).models["dust"]
    nu = band.freqs_ghz
    t_rj = mbb_rj(nu, sky.DUST_FREQ_REF_GHZ) * 1e-6  # K_RJ per uK_RJ of template
    single = np.trapezoid(t_rj, nu) / np.trapezoid(rj_per_cmb(nu), nu)
    constant_etendue = np.trapezoid(nu**2 * t_rj, nu) / np.trapezoid(nu**2 * rj_per_cmb(nu), nu)
    factors = sky.band_factors(model, band)
    np.testing.assert_allclose(factors, single, rtol=1e-5)
    np.testing.assert_allclose(
        sky.band_factors(model, band, single_mode=False), constant_etendue, rtol=1e-5
    )
    assert abs(single / constant_etendue - 1) > 1e-3  # the two conventions differ


def test_factor_method_equals_full_pysm3_evaluation():
    """Template x band factor == pysm3 get_emission on the full maps (constant SED)."""
    import pysm3
    import pysm3.units as u

    nside = 8
    band = top_hat_bandpass(140.0, 42.0)
    fg = sky.foreground_models(nside, MASTER)
    freqs, weights = sky.pysm_bandpass(band)
    conversion = pysm3.bandpass_unit_conversion(freqs, weights, u.K_CMB, cut=0.0)
    direct = sum(
        (model.get_emission(freqs, weights) * conversion).to_value(u.K_CMB)
        for model in fg.models.values()
    )
    np.testing.assert_allclose(
        sky.foreground_emission(band, nside, MASTER), direct, rtol=1e-10, atol=0
    )


def test_offline_templates_fixed_galactic_and_flagged(caplog):
    nside = 16
    sky.offline_templates.cache_clear()
    first = {k: v.copy() for k, v in sky.offline_templates(nside, MASTER).items()}
    sky.offline_templates.cache_clear()
    again = sky.offline_templates(nside, MASTER)
    other = sky.offline_templates(nside, MASTER + 1)
    for component in sky.COMPONENTS:
        np.testing.assert_array_equal(first[component], again[component])
        assert not np.allclose(first[component], other[component])
    # independent of the realisation seed
    ch = make_channel("A-100", 100.0, 23.0, 60.0)
    s1 = sky.channel_sky_map(ch, nside, 47, 0.0, MASTER, 1)
    s2 = sky.channel_sky_map(ch, nside, 47, 0.0, MASTER, 2)
    np.testing.assert_array_equal(s1["foreground"], s2["foreground"])
    assert not np.allclose(s1["cmb"], s2["cmb"])
    # bright Galactic plane, faint poles; positive intensity
    sin_b = hp.pix2vec(nside, np.arange(hp.nside2npix(nside)))[2]
    plane, poles = np.abs(sin_b) < np.sin(np.radians(10)), np.abs(sin_b) > np.sin(np.radians(60))
    for component, template in first.items():
        assert np.all(template[0] > 0)
        polarised = np.hypot(template[1], template[2])
        assert template[0][plane].mean() > 4 * template[0][poles].mean(), component
        assert polarised[plane].mean() > 4 * polarised[poles].mean(), component
        median_p = np.median(polarised / template[0])
        assert 0.02 < median_p < 0.4, (component, median_p)
    # flagged, with a warning when the models are built
    assert sky.foreground_source() == sky.OFFLINE_SOURCE
    assert "NOT pysm3" in sky.OFFLINE_SOURCE
    sky._foreground_models.cache_clear()
    with caplog.at_level(logging.WARNING, logger="hwp_tes_systematics.sky"):
        sky.foreground_models(nside, MASTER)
    assert "NOT pysm3 data" in caplog.text


# ------------------------------------------------------------------ pysm3 data
@pytest.fixture
def no_download(monkeypatch):
    """Any attempt of astropy to fetch remote data fails the test."""
    import astropy.utils.data

    def refuse(*args, **kwargs):
        raise AssertionError(f"download attempted: {args}")

    monkeypatch.setattr(astropy.utils.data, "download_file", refuse)
    monkeypatch.setattr(astropy.utils.data, "get_pkg_data_filename", refuse)


def test_pysm_local_data_missing_files_raise_clear_error(tmp_path, monkeypatch, no_download):
    band = top_hat_bandpass(100.0, 23.0)
    with pytest.raises(FileNotFoundError, match=r"pysm_2/dust_t_new\.fits"):
        sky.foreground_source(tmp_path)
    with pytest.raises(FileNotFoundError, match="nothing is downloaded"):
        sky.foreground_map(band, 8, MASTER, 0.0, pysm_local_data=tmp_path)
    monkeypatch.setenv("PYSM_LOCAL_DATA", str(tmp_path))
    with pytest.raises(FileNotFoundError, match=str(tmp_path)):
        sky.foreground_source()


@pytest.mark.slow
def test_pysm_local_data_templates_are_used(tmp_path, no_download):
    """Fake d0/s0 template files (constant maps) go through pysm3.Sky and its d0 SED."""
    folder = tmp_path / "pysm_2"
    folder.mkdir()
    values = {"dust": (100.0, 10.0, -5.0), "synch": (50.0, 4.0, 2.0)}
    for prefix, (i, q, u) in values.items():
        for stokes, value in zip("tqu", (i, q, u)):
            hp.write_map(
                str(folder / f"{prefix}_{stokes}_new.fits"),
                np.full(hp.nside2npix(8), value),
                dtype=np.float64,
                column_units="uK_RJ",
            )
    assert sky.foreground_source(tmp_path) == sky.PYSM_SOURCE
    dust = sky.foreground_emission(
        top_hat_bandpass(353.0, 0.2), 4, MASTER, tmp_path, unit="uK_RJ", components=["dust"]
    )
    assert dust.shape == (3, hp.nside2npix(4))
    # d0: Q, U referenced at 353 GHz, I at 545 GHz
    np.testing.assert_allclose(dust[1:], [[10.0], [-5.0]] * np.ones_like(dust[1:]), rtol=1e-4)
    np.testing.assert_allclose(dust[0], 100.0 * mbb_rj(353.0, 545.0), rtol=1e-4)
    band = top_hat_bandpass(100.0, 23.0)
    smoothed = sky.foreground_map(band, 4, MASTER, 600.0, tmp_path)
    unsmoothed = sky.foreground_map(band, 4, MASTER, 0.0, tmp_path)
    np.testing.assert_allclose(smoothed[0], unsmoothed[0], rtol=1e-2)  # constant I (nside 4)
    assert np.all(unsmoothed[0] > 0)


# ------------------------------------------------------------------------- I/O
def test_write_read_round_trip(tmp_path):
    from astropy.io import fits

    nside = 16
    maps = np.random.default_rng(0).normal(size=(3, hp.nside2npix(nside))) * 1e-5
    path = tmp_path / "sky" / "total.fits"
    sky.write_sky_map(path, maps, {"SEED": 3}, foreground_source=sky.OFFLINE_SOURCE)
    np.testing.assert_array_equal(sky.read_sky_map(path, nside=nside), maps)
    header = fits.getheader(path, 1)
    assert header["COORDSYS"] == "G"
    assert header["ORDERING"] == "RING"
    assert [header[f"TUNIT{i}"] for i in (1, 2, 3)] == ["K_CMB"] * 3
    assert header[sky.FOREGROUND_SOURCE_KEY] == sky.OFFLINE_SOURCE
    assert header["SEED"] == 3
    assert sorted(p.name for p in path.parent.iterdir()) == ["total.fits"]  # no temporaries
    with pytest.raises(ValueError, match=r"total\.fits.*nside = 32"):
        sky.read_sky_map(path, nside=32)


def test_wrong_shapes_raise_naming_the_file(tmp_path):
    single = tmp_path / "single.fits"
    hp.write_map(str(single), np.zeros(hp.nside2npix(4)))
    with pytest.raises(ValueError, match=r"single\.fits.*3 fields"):
        sky.read_sky_map(single)
    not_fits = tmp_path / "junk.fits"
    not_fits.write_text("not a FITS file")
    with pytest.raises(ValueError, match=r"junk\.fits"):
        sky.read_sky_map(not_fits)
    with pytest.raises(ValueError, match=r"bad\.fits.*\(3, npix\)"):
        sky.write_sky_map(tmp_path / "bad.fits", np.zeros((2, 192)), {})
    assert not (tmp_path / "bad.fits").exists()


def test_maps_carry_their_convention_and_iau_input_is_converted(tmp_path):
    """POLCCONV, FWHM, FREQ on every map written; an IAU map is read with U negated."""
    from astropy.io import fits

    nside = 8
    maps = np.random.default_rng(1).normal(size=(3, hp.nside2npix(nside)))
    path = tmp_path / "cosmo.fits"
    sky.write_sky_map(path, maps, fwhm_arcmin=30.8, freq_ghz=140.0)
    header = fits.getheader(path, 1)
    assert header["POLCCONV"] == "COSMO"
    assert header["FWHM"] == 30.8 and header["FREQ"] == 140.0
    iau = tmp_path / "iau.fits"
    sky.write_sky_map(iau, maps, {"POLCCONV": "IAU"})
    converted = sky.read_sky_map(iau)
    np.testing.assert_array_equal(converted[:2], maps[:2])
    np.testing.assert_array_equal(converted[2], -maps[2])
    odd = tmp_path / "odd.fits"
    sky.write_sky_map(odd, maps, {"POLCCONV": "HEALPIX"})
    with pytest.raises(ValueError, match=r"odd\.fits.*POLCCONV"):
        sky.read_sky_map(odd)
