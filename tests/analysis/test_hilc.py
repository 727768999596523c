"""Harmonic ILC: bins, beams, map -> a_lm, weights, CMB preservation, foreground removal."""

import itertools

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.analysis import hilc, spectra

LMAX = 95  # nside 32


def gaussian_field(rng, cl, lmax=LMAX):
    """(nalm,) a_lm of an isotropic Gaussian field of spectrum ``cl`` (m = 0 real)."""
    ell, m = hp.Alm.getlm(lmax)
    z = (rng.standard_normal(ell.size) + 1j * rng.standard_normal(ell.size)) / np.sqrt(2.0)
    z[m == 0] = rng.standard_normal(np.count_nonzero(m == 0))
    return np.sqrt(np.broadcast_to(cl, (lmax + 1,))[ell]) * z


def teb_field(rng, cl, lmax=LMAX):
    """(3, nalm) independent T, E, B fields of spectrum ``cl``; E, B zero at ell < 2."""
    alm = np.array([gaussian_field(rng, cl, lmax) for _ in range(3)])
    ell = hp.Alm.getlm(lmax)[0]
    alm[1:, ell < 2] = 0
    return alm


def power_in_bins(alm, bins, lmax=LMAX):
    """sum over the modes of each bin of |a_lm|^2 (both signs of m), per bin."""
    ell, m = hp.Alm.getlm(lmax)
    mult = np.where(m == 0, 1.0, 2.0)
    return np.array(
        [np.sum(mult * np.abs(alm) ** 2 * ((ell >= lo) & (ell < hi))) for lo, hi in bins]
    )


# ---------------------------------------------------------------------------- bins
def test_multipole_bins_cover_range_and_last_bin_shorter():
    bins = hilc.multipole_bins(2, 11, 4)
    assert bins == [(2, 6), (6, 10), (10, 12)]
    assert hilc.multipole_bins(2, 9, 4) == [(2, 6), (6, 10)]
    covered = np.concatenate([np.arange(lo, hi) for lo, hi in hilc.multipole_bins(2, 95, 7)])
    np.testing.assert_array_equal(covered, np.arange(2, 96))
    assert hilc.bins_from_edges([2, 10, 30, 51]) == [(2, 10), (10, 30), (30, 51)]


@pytest.mark.parametrize("edges", [[10, 5], [3], [2, 2, 5], [2.5, 6]])
def test_bad_edges_raise(edges):
    with pytest.raises(ValueError):
        hilc.bins_from_edges(edges)


def test_bad_multipole_bins_raise():
    with pytest.raises(ValueError):
        hilc.multipole_bins(10, 5, 4)
    with pytest.raises(ValueError):
        hilc.multipole_bins(2, 10, 0)
    with pytest.raises(ValueError, match="beyond lmax"):
        hilc.ilc_weights(np.zeros((2, hp.Alm.getsize(10))), [(2, 20)], 10)


# ---------------------------------------------------------------------------- beams
@pytest.mark.parametrize("fwhm_a, fwhm_b", [(60.0, 180.0), (180.0, 120.0), (0.0, 100.0)])
def test_deconvolution_to_common_beam_equals_direct_smoothing(fwhm_a, fwhm_b):
    rng = np.random.default_rng(3)
    alm = teb_field(rng, 1.0)
    beam = {
        f: hp.gauss_beam(np.radians(f / 60), lmax=LMAX, pol=True)[:, :3] for f in (fwhm_a, fwhm_b)
    }
    smoothed_a = np.array([hp.almxfl(alm[i], beam[fwhm_a][:, i]) for i in range(3)])
    direct_b = np.array([hp.almxfl(alm[i], beam[fwhm_b][:, i]) for i in range(3)])
    result = hilc.deconvolve_to_common_beam(smoothed_a, fwhm_a, fwhm_b, LMAX)
    ell = hp.Alm.getlm(LMAX)[0]
    for i in range(3):
        good = beam[fwhm_a][ell, i] > 1e-3
        assert good.sum() > 1000
        scale = np.max(np.abs(direct_b[i]))
        np.testing.assert_allclose(result[i, good], direct_b[i, good], rtol=0, atol=1e-10 * scale)
    # T and E/B use different beam columns (spin-2 factor): swapping them must differ
    wrong = hp.almxfl(smoothed_a[1], beam[fwhm_b][:, 0] / beam[fwhm_a][:, 0])
    assert np.max(np.abs(wrong - direct_b[1])) > 1e-6 * np.max(np.abs(direct_b[1]))


def test_deconvolution_rejects_bad_inputs():
    alm = np.zeros((3, hp.Alm.getsize(LMAX)), complex)
    with pytest.raises(ValueError):
        hilc.deconvolve_to_common_beam(alm, -1.0, 30.0, LMAX)
    with pytest.raises(ValueError):
        hilc.deconvolve_to_common_beam(alm[:2], 10.0, 30.0, LMAX)
    with pytest.raises(ValueError):
        hilc.deconvolve_to_common_beam(alm, 10.0, 30.0, LMAX + 1)


# ---------------------------------------------------------------------- maps -> a_lm
def test_maps_to_alm_full_sky_matches_healpy_and_handles_unseen():
    nside = 16
    rng = np.random.default_rng(4)
    maps = rng.standard_normal((3, hp.nside2npix(nside)))
    full = hilc.maps_to_alm(maps, np.ones(maps.shape[1]), 2 * nside)
    ref = hp.map2alm(maps, lmax=2 * nside, pol=True, iter=hilc.MAP2ALM_ITER)
    np.testing.assert_allclose(full, ref, rtol=0, atol=1e-12)

    mask = np.ones(maps.shape[1])
    mask[:100] = 0.0
    with_unseen = maps.copy()
    with_unseen[1, :50] = hp.UNSEEN
    zeroed = maps * mask
    np.testing.assert_allclose(
        hilc.maps_to_alm(with_unseen, mask, 2 * nside),
        hp.map2alm(zeroed, lmax=2 * nside, pol=True, iter=hilc.MAP2ALM_ITER),
        rtol=0,
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="weights in"):
        hilc.maps_to_alm(maps, 2 * np.ones(maps.shape[1]), 2 * nside)
    mask[10] = 0.5  # a weight on an UNSEEN pixel: refused
    with pytest.raises(ValueError, match="UNSEEN"):
        hilc.maps_to_alm(with_unseen, mask, 2 * nside)


# ------------------------------------------------------------------------ the ILC
@pytest.fixture(scope="module")
def sky():
    """CMB + foreground (SED s_i, 10x the CMB amplitude) + white noise in 6 channels."""
    rng = np.random.default_rng(2024)
    cl_cmb = 1.0 / (1.0 + np.arange(LMAX + 1) / 20.0) ** 2
    cmb = teb_field(rng, cl_cmb)
    fg = 10.0 * teb_field(rng, cl_cmb)
    sed = np.array([0.2, 0.5, 1.0, 2.0, 4.0, 8.0])
    sigma = np.array([0.3, 0.6, 0.15, 0.9, 0.45, 0.3])
    noise = np.array([s * teb_field(rng, 0.1) for s in sigma])
    foregrounds = sed[:, None, None] * fg
    return {
        "cmb": cmb,
        "fg": fg,
        "sed": sed,
        "sigma": sigma,
        "cl_cmb": cl_cmb,
        "foregrounds": foregrounds,
        "noise": noise,
        "total": cmb + foregrounds + noise,
    }


def test_empirical_covariance_counts_both_signs_of_m():
    """Brute force over -ell <= m <= ell with a_l,-m = (-1)^m a_lm^* (real fields)."""
    lmax = 12
    rng = np.random.default_rng(5)
    alms = np.array([gaussian_field(rng, 1.0 + k, lmax) for k in range(3)])
    bins = [(2, 6), (6, 13)]
    cov, n_modes = hilc.empirical_covariance(alms, bins, lmax)
    for b, (lo, hi) in enumerate(bins):
        total, count = np.zeros((3, 3), complex), 0
        for ell in range(lo, hi):
            for m in range(-ell, ell + 1):
                a = alms[:, hp.Alm.getidx(lmax, ell, abs(m))]
                a = a if m >= 0 else (-1) ** m * a.conj()
                total += np.outer(a, a.conj())
                count += 1
        assert n_modes[b] == count
        np.testing.assert_allclose(cov[b], total.real / count, rtol=1e-12)
        assert np.max(np.abs(total.imag)) < 1e-12 * np.max(np.abs(total))


def test_weights_from_covariance_match_direct_solve_for_badly_scaled_channels():
    rng = np.random.default_rng(6)
    n_ch = 8
    x = rng.standard_normal((n_ch, 40))
    scale = np.logspace(-6, 6, n_ch)  # e.g. K_CMB amplitudes from 40 to 402 GHz
    cov = scale[:, None] * (x @ x.T / 40) * scale[None, :]
    expected = np.linalg.solve(cov, np.ones(n_ch))
    expected /= expected.sum()
    np.testing.assert_allclose(hilc.weights_from_covariance(cov), expected, rtol=1e-9, atol=0)


def test_weights_sum_to_one_per_bin_for_t_e_b(sky):
    bins = hilc.multipole_bins(2, LMAX, 8)
    _, weights = hilc.harmonic_ilc(sky["total"], bins, LMAX)
    assert weights.shape == (3, len(bins), 6)
    np.testing.assert_allclose(weights.sum(axis=-1), 1.0, rtol=0, atol=1e-12)
    # the weights are not trivial: they differ between bins and from the plain average
    assert np.ptp(weights[2, :, 0]) > 1e-3
    assert np.max(np.abs(weights - 1 / 6)) > 0.1


def test_cmb_preserved_exactly_output_is_cmb_plus_weighted_residuals(sky):
    bins = hilc.multipole_bins(2, LMAX, 8)
    alm_cmb, weights = hilc.harmonic_ilc(sky["total"], bins, LMAX)
    residual = hilc.apply_ilc(sky["foregrounds"] + sky["noise"], weights, bins, LMAX)
    ell = hp.Alm.getlm(LMAX)[0]
    inside = ell >= 2
    expected = np.where(inside, sky["cmb"], 0)
    scale = np.max(np.abs(sky["cmb"]))
    np.testing.assert_allclose(alm_cmb - residual, expected, rtol=0, atol=1e-12 * scale)
    assert np.all(alm_cmb[:, ~inside] == 0)  # ell outside every bin: 0
    # linearity: the same weights on the CMB alone (unit SED) return the CMB
    cmb_channels = np.broadcast_to(sky["cmb"], sky["total"].shape)
    np.testing.assert_allclose(
        hilc.apply_ilc(cmb_channels, weights, bins, LMAX), expected, rtol=0, atol=1e-12 * scale
    )
    # Per bin, the regression slope of the output on the input CMB is 1 up to the known
    # ILC bias: the empirical covariance of n_b modes cancels part of the CMB against its
    # chance correlation with the other components, slope ~ 1 - (n_ch - 1) / n_b.
    deviations = []
    for s in range(3):
        _, n_modes = hilc.empirical_covariance(sky["total"][:, s], bins, LMAX, min(s, 1) * 2)
        for (lo, hi), n_b in zip(bins, n_modes):
            sel = (ell >= lo) & (ell < hi)
            cmb = sky["cmb"][s, sel]
            slope = np.vdot(cmb, alm_cmb[s, sel]).real / np.vdot(cmb, cmb).real
            deviations.append(slope - (1 - 5 / n_b))
    assert np.max(np.abs(deviations)) < 0.05  # scatter 0.011 per bin here
    assert abs(np.mean(deviations)) < 0.006


def test_foreground_with_other_sed_is_removed_without_noise(sky):
    bins = hilc.multipole_bins(2, LMAX, 10)
    data = sky["cmb"] + sky["foregrounds"]  # rank-2 covariance in 6 channels
    alm_cmb, weights = hilc.harmonic_ilc(data, bins, LMAX)
    np.testing.assert_allclose(weights.sum(axis=-1), 1.0, atol=1e-12)
    fg_power = power_in_bins(sky["fg"][2], bins)
    residual_power = power_in_bins(alm_cmb[2] - sky["cmb"][2], bins)
    assert np.all(residual_power < 1e-3 * fg_power)
    # the foreground response sum_i w_i s_i is ~ 0 (a plain average would give 2.6)
    assert np.all(np.abs(weights @ sky["sed"]) < 0.03)
    average = data.mean(axis=0)
    assert np.all(power_in_bins(average[2] - sky["cmb"][2], bins) > 1.0 * fg_power)


def test_weights_approach_the_minimum_variance_solution(sky):
    # one wide bin (9212 modes) of E: the known covariance per mode is
    # C = C_cmb e e^T + 100 C_cmb s s^T + N, averaged over the bin with (2 ell + 1)
    bins = [(2, LMAX + 1)]
    weights = hilc.ilc_weights(sky["total"][:, 1], bins, LMAX, min_ell=2)[0]
    ell = np.arange(2, LMAX + 1)
    mean_cl = np.sum((2 * ell + 1) * sky["cl_cmb"][2:]) / np.sum(2 * ell + 1)
    ones = np.ones(6)
    cov = mean_cl * (np.outer(ones, ones) + 100 * np.outer(sky["sed"], sky["sed"]))
    cov += np.diag(0.1 * sky["sigma"] ** 2)
    expected = np.linalg.solve(cov, ones)
    expected /= expected.sum()
    assert np.max(np.abs(weights - expected)) < 0.03
    assert weights @ cov @ weights < 1.02 * (expected @ cov @ expected)


def test_output_variance_not_larger_than_best_single_channel(sky):
    bins = hilc.multipole_bins(2, LMAX, 8)
    alm_cmb, _ = hilc.harmonic_ilc(sky["total"], bins, LMAX)
    for s in range(3):
        out = power_in_bins(alm_cmb[s], bins)
        channels = np.array([power_in_bins(a, bins) for a in sky["total"][:, s]])
        assert np.all(out <= channels.min(axis=0) * (1 + 1e-12))
        assert np.all(out < 0.9 * channels.min(axis=0))  # strictly better here


def test_rank_deficient_bin_raises_unless_regularised(sky):
    data = sky["total"][:, 0]
    bins = [(2, 4), (4, 40)]  # [2, 4) has 5 + 7 = 12 modes
    many = np.concatenate([data, data + 0.1 * sky["noise"][:, 0]])  # 12 channels: OK
    hilc.ilc_weights(many, bins, LMAX)
    more = np.concatenate([many, data[:1] + sky["noise"][1:2, 0]])  # 13 channels
    with pytest.raises(ValueError, match=r"\[2, 4\) has 12 modes.*fewer than the 13 channels"):
        hilc.ilc_weights(more, bins, LMAX)
    for regularisation in ("pinv", 1e-3):
        weights = hilc.ilc_weights(more, bins, LMAX, regularisation=regularisation)
        np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    with pytest.raises(ValueError):
        hilc.ilc_weights(more, bins, LMAX, regularisation="tikhonov")
    # E and B: ell < 2 do not count as modes
    with pytest.raises(ValueError, match="has 5 modes"):
        hilc.ilc_weights(sky["total"][:, 1], [(0, 3)], LMAX, min_ell=2)


def test_zero_power_channel_raises(sky):
    data = sky["total"][:, 0].copy()
    data[3] = 0
    with pytest.raises(ValueError, match=r"channel\(s\) \[3\] have zero power"):
        hilc.ilc_weights(data, [(2, 40)], LMAX)


def test_apply_weights_zero_outside_bins_and_checks_shapes(sky):
    bins = [(10, 20), (30, 40)]
    weights = np.full((2, 6), 1 / 6)
    out = hilc.apply_weights(sky["total"][:, 0], weights, bins, LMAX)
    ell = hp.Alm.getlm(LMAX)[0]
    inside = ((ell >= 10) & (ell < 20)) | ((ell >= 30) & (ell < 40))
    assert np.all(out[~inside] == 0)
    np.testing.assert_allclose(out[inside], sky["total"][:, 0, inside].mean(axis=0))
    with pytest.raises(ValueError):
        hilc.apply_weights(sky["total"][:, 0], weights[:, :5], bins, LMAX)
    with pytest.raises(ValueError):
        hilc.apply_weights(sky["total"][:, 0], weights[:1], bins, LMAX)


def test_map_level_pipeline_with_beams_mask_and_unseen():
    """Maps with different beams and UNSEEN pixels -> common beam -> HILC -> CMB."""
    nside, lmax = 32, 64
    rng = np.random.default_rng(7)
    cl = 1.0 / (1.0 + np.arange(lmax + 1) / 10.0) ** 2
    cmb, fg = teb_field(rng, cl, lmax), 10.0 * teb_field(rng, cl, lmax)
    fwhms = [70.0, 100.0, 130.0, 160.0, 200.0]
    seds = [0.3, 0.7, 1.5, 3.0, 6.0]
    maps = []
    for fwhm, sed in zip(fwhms, seds):
        b = hp.gauss_beam(np.radians(fwhm / 60), lmax=lmax, pol=True)
        alm = np.array([hp.almxfl(cmb[i] + sed * fg[i], b[:, i]) for i in range(3)])
        m = hp.alm2map(alm, nside, lmax=lmax, pixwin=False)
        maps.append(m)
    maps[1][:, 100:200] = hp.UNSEEN
    maps[3][2, 5000:5100] = hp.UNSEEN
    binary = spectra.common_mask(maps, 0.0)
    assert np.count_nonzero(~binary) == 200
    mask = binary.astype(float)
    alms = hilc.channel_alms(maps, fwhms, mask, lmax)  # common beam = 200 arcmin
    bins = hilc.multipole_bins(2, 40, 6)
    alm_cmb, _ = hilc.harmonic_ilc(alms, bins, lmax)
    # reference: the CMB at the common beam, masked the same way
    b_common = hp.gauss_beam(np.radians(200 / 60), lmax=lmax, pol=True)
    cmb_common = np.array([hp.almxfl(cmb[i], b_common[:, i]) for i in range(3)])
    cmb_masked = hilc.maps_to_alm(hp.alm2map(cmb_common, nside, lmax=lmax), mask, lmax)
    fg_masked = hilc.maps_to_alm(
        hp.alm2map(np.array([hp.almxfl(fg[i], b_common[:, i]) for i in range(3)]), nside, lmax),
        mask,
        lmax,
    )
    for s in range(3):
        residual = power_in_bins(alm_cmb[s] - cmb_masked[s], bins, lmax)
        assert np.all(residual < 1e-3 * power_in_bins(fg_masked[s], bins, lmax))


def test_low_ell_bins_are_merged_until_enough_modes():
    from hwp_tes_systematics.analysis.hilc import merge_bins_for_modes, multipole_bins

    bins = multipole_bins(2, 128, 10)
    merged = merge_bins_for_modes(bins, fsky=0.1, n_channels=22, min_modes_per_channel=10)
    assert merged[0][0] == 2 and merged[-1][1] == bins[-1][1]
    for start, stop in merged:
        assert 0.1 * sum(2 * ell + 1 for ell in range(start, stop)) >= 220
    assert all(a[1] == b[0] for a, b in itertools.pairwise(merged))  # contiguous
    assert merge_bins_for_modes(bins, 1.0, 1, 1) == bins  # nothing to merge
