"""Several map-makers in one fixed TOD pass (fixed_maps.fixed_passes, simulation.fixed_pass_*).

One M1-140 pair, six hours at 19 Hz, the sky scanned at nside 32: the pass also bins at
nside 16 and without baselines. Each variant must be what a pass of its own gives: the
no-baseline map-maker that of a separate pass without baselines (the HWP-harmonic fit
without a constant), the primary one that of a separate pass with baselines (both to
round-off: one filtering gives both fits, hwpss_removal.offset_residual), and the nside-16
normal equations the sums of their nside-32 children (the same samples, coarser pixels).
"""

import dataclasses

import healpy as hp
import numpy as np
import pytest
from helpers import m1_140_pair, pipeline_settings

from hwp_tes_systematics import sky
from hwp_tes_systematics.simulation import fixed_maps, tod_maps
from hwp_tes_systematics.simulation.hwpss_removal import offset_residual, remove_hwp_harmonics
from hwp_tes_systematics.sky import cmb as sky_cmb

pytestmark = pytest.mark.slow

SCAN_NSIDE, COARSE_NSIDE = 32, 16
LMAX = 3 * SCAN_NSIDE - 1
VARIANTS = [(COARSE_NSIDE, 60.0), (SCAN_NSIDE, None), (COARSE_NSIDE, None)]
FIELDS = ("nosys", "template_terms", "foreground_reference", "matrix", "moments", "hits")


@pytest.fixture(scope="module")
def passes():
    """({variant: FixedMaps} of one pass, {variant: FixedMaps} of separate passes, the
    same pass accumulated in NESTED pixels, the passes' arguments)."""
    simulator = m1_140_pair(6 * 3600.0, 3 * 3600.0, SCAN_NSIDE, 19.0, noise_model="keshner")
    channel = simulator.channel
    settings = pipeline_settings(simulator, seed=fixed_maps.NOISE_REFERENCE_SEED, noise_scale=0.0)
    cls = np.zeros((4, LMAX + 1))
    cls[:3, 2:] = 1e-9 * (np.arange(2, LMAX + 1) / 10.0) ** -2.5
    foreground = hp.alm2map(sky.gaussian_alm(cls, LMAX, np.random.default_rng(3)), SCAN_NSIDE)
    foreground[0] += 3e-3  # an intensity offset as large as the dipole
    transfer_alm = sky_cmb.transfer_cmb_alm(LMAX, 0.0, 7, channel.fwhm_arcmin)
    arguments = (simulator, settings, foreground, transfer_alm, True, LMAX)
    together = fixed_maps.fixed_passes(*arguments, extra_variants=VARIANTS)
    tod_maps.NESTED_FROM_NSIDE, ring_from = 1, tod_maps.NESTED_FROM_NSIDE
    try:  # the same accumulated in NESTED order (what nside >= 256 does)
        nested = fixed_maps.fixed_passes(*arguments, extra_variants=VARIANTS)
    finally:
        tod_maps.NESTED_FROM_NSIDE = ring_from
    no_baselines = dataclasses.replace(settings, baseline_length_s=None)
    separate = {
        (SCAN_NSIDE, 60.0): fixed_maps.fixed_pass(*arguments),
        (SCAN_NSIDE, None): fixed_maps.fixed_pass(simulator, no_baselines, *arguments[2:]),
    }
    return together, separate, nested, arguments


def assert_same(fixed, reference, label, rtol=1e-9):
    for name in FIELDS:
        value, expected = getattr(fixed, name), getattr(reference, name)
        scale = np.abs(expected[np.abs(expected) < 1e20]).max()
        np.testing.assert_allclose(value, expected, rtol=0, atol=rtol * scale, err_msg=name)
    np.testing.assert_array_equal(fixed.good, reference.good, err_msg=f"{label}: good")
    # the calibration TODs are filtered in single precision (tod_maps.CALIBRATION_DTYPE):
    # T_ell and S_ell (of order 1) to ~1e-5, not to double precision's round-off
    for name in ("transfer", "noise_shaping", "noise_h_shaping"):
        np.testing.assert_allclose(
            getattr(fixed, name), getattr(reference, name), rtol=0, atol=2e-5, err_msg=name
        )


def test_offset_fit_is_the_fit_without_offset_then_the_constant_projected_out():
    rng = np.random.default_rng(1)
    angle = np.cumsum(np.full(5000, 0.37))
    tod = rng.normal(size=(3, 5000)) + 2.0 + np.cos(2 * angle)
    u = offset_residual(angle, (2, 4))
    joint = remove_hwp_harmonics(tod, angle, (2, 4), offset=True)
    split = remove_hwp_harmonics(tod, angle, (2, 4)) - np.outer(tod @ u / (u @ u), u)
    np.testing.assert_allclose(split, joint, rtol=0, atol=1e-12)


def test_nested_accumulation_gives_the_same_maps_bit_for_bit(passes):
    """Accumulating in NESTED pixels and reordering to RING at the end changes no number."""
    together, _, nested, _ = passes
    for variant, fixed in together.items():
        for name in (*FIELDS, "condition", "good", "transfer", "noise_shaping", "noise_h_shaping"):
            np.testing.assert_array_equal(
                getattr(nested[variant], name), getattr(fixed, name), err_msg=f"{variant} {name}"
            )


def test_every_variant_is_there(passes):
    together, *_ = passes
    assert set(together) == {(SCAN_NSIDE, 60.0), *VARIANTS}
    for (nside, _), fixed in together.items():
        assert fixed.nosys.shape == (3, hp.nside2npix(nside))
        assert fixed.moments.shape[1] == hp.nside2npix(nside)


def test_baseline_variants_equal_their_own_passes(passes):
    together, separate, *_ = passes
    for variant, reference in separate.items():
        assert_same(together[variant], reference, str(variant))
    # and the two map-makers do differ (the no-baseline one keeps the offsets)
    seen = together[(SCAN_NSIDE, None)].good & together[(SCAN_NSIDE, 60.0)].good
    with_b, without = (together[(SCAN_NSIDE, b)].nosys[0, seen] for b in (60.0, None))
    assert np.abs(with_b - without).max() > 1e-4


@pytest.mark.parametrize("baseline", [60.0, None])
def test_coarse_variant_bins_the_same_samples_in_coarser_pixels(passes, baseline):
    """The nside-16 matrix, hits and HWPSS moments are the sums over the four nside-32
    children; its no-systematics map solves the summed equations of the children."""
    together, *_ = passes
    fine, coarse = together[(SCAN_NSIDE, baseline)], together[(COARSE_NSIDE, baseline)]
    parent = hp.nest2ring(
        COARSE_NSIDE, hp.ring2nest(SCAN_NSIDE, np.arange(hp.nside2npix(SCAN_NSIDE))) // 4
    )

    def children_sum(values):  # pixels on the last axis
        total = np.zeros((*values.shape[:-1], hp.nside2npix(COARSE_NSIDE)))
        np.add.at(total, (..., parent), values)
        return total

    np.testing.assert_array_equal(children_sum(fine.hits), coarse.hits)
    scale = np.abs(coarse.matrix).max()  # sums of cosines: round-off relative to the largest
    np.testing.assert_allclose(children_sum(fine.matrix), coarse.matrix, rtol=0, atol=1e-13 * scale)
    summed_moments = np.moveaxis(children_sum(np.moveaxis(fine.moments, 1, -1)), -1, 1)
    np.testing.assert_allclose(summed_moments, coarse.moments, rtol=0, atol=1e-13 * scale)
    # rhs of each fine pixel is M m; where every observed child is solved, the parent's
    # map is M_parent^-1 sum rhs
    observed_children_solved = children_sum((fine.hits > 0) & ~fine.good) == 0
    check = observed_children_solved & coarse.good
    assert check.sum() > 100
    fine_rhs = np.zeros((3, fine.good.size))
    good = np.flatnonzero(fine.good)
    fine_rhs[:, good] = np.einsum("pij,jp->ip", fine.matrices(good), fine.nosys[:, good])
    coarse_rhs = children_sum(fine_rhs)[:, check]
    solved = np.linalg.solve(coarse.matrices(np.flatnonzero(check)), coarse_rhs.T[..., None])
    np.testing.assert_allclose(solved[..., 0].T, coarse.nosys[:, check], rtol=1e-8, atol=1e-12)


def test_map_makers_of_one_resolution_share_one_copy_of_the_moments(passes, tmp_path):
    together, *_ = passes
    holder, sharer = together[(SCAN_NSIDE, 60.0)], together[(SCAN_NSIDE, None)]
    attributes = {"detectors": ["a", "b"], "nside": SCAN_NSIDE}
    fixed_maps.write_fixed_maps(tmp_path / "holder.h5", holder, attributes)
    fixed_maps.write_fixed_maps(tmp_path / "sharer.h5", sharer, attributes, moments_in="holder.h5")
    assert (tmp_path / "sharer.h5").stat().st_size < 0.6 * (tmp_path / "holder.h5").stat().st_size
    assert fixed_maps.moments_file(tmp_path / "sharer.h5") == tmp_path / "holder.h5"
    read, _ = fixed_maps.read_fixed_maps(tmp_path / "sharer.h5")
    np.testing.assert_array_equal(read.moments, sharer.moments)
    np.testing.assert_array_equal(read.nosys, sharer.nosys)
    # a channel without systematics stores neither (zero) template terms nor moments
    plain = dataclasses.replace(
        sharer,
        carries_systematics=False,
        moments=np.zeros(0),
        template_terms=0 * sharer.template_terms,
    )
    fixed_maps.write_fixed_maps(tmp_path / "plain.h5", plain, attributes)
    read, _ = fixed_maps.read_fixed_maps(tmp_path / "plain.h5")
    np.testing.assert_array_equal(read.template_terms, plain.template_terms)
    assert read.moments.size == 0


def test_calibration_in_single_precision_measures_what_double_does(passes, monkeypatch):
    """The calibration TODs filtered in float32 (tod_maps.CALIBRATION_DTYPE) give T_ell,
    S_ell and S^h_ell within 2e-5 of a float64 filtering, and leave the maps untouched."""
    _, separate, _, arguments = passes
    monkeypatch.setattr(tod_maps, "CALIBRATION_DTYPE", np.float64)
    double = fixed_maps.fixed_pass(*arguments)
    single = separate[(SCAN_NSIDE, 60.0)]
    for name in ("nosys", "template_terms", "matrix", "moments"):
        np.testing.assert_array_equal(getattr(single, name), getattr(double, name), err_msg=name)
    for name in ("transfer", "noise_shaping", "noise_h_shaping"):
        difference = np.abs(getattr(single, name) - getattr(double, name)).max()
        assert 0 < difference < 2e-5, (name, difference)


def test_a_demodulated_variant_shares_the_pass_and_measures_its_filter(passes):
    """A demodulated map-maker at the scan's resolution in the same pass: its white-noise
    reference M and HWPSS moments are the binned variant's (the seeds draw the same binned
    white noise), its nosys map the demodulated one; the demodulation's T_ell and S_ell
    are its own (the low-pass below 0.95 f_HWP keeps the sky band: T_BB near the binned
    map-maker's above the notch's ell ~40, not equal)."""
    together, _, _, arguments = passes
    demodulated = fixed_maps.fixed_passes(
        *arguments, extra_variants=VARIANTS, demodulated_variants=[(SCAN_NSIDE, 60.0)]
    )
    fixed = demodulated[(SCAN_NSIDE, 60.0, "demodulated")]
    binned = together[(SCAN_NSIDE, 60.0)]
    np.testing.assert_allclose(fixed.matrix, binned.matrix, rtol=1e-12)
    np.testing.assert_allclose(fixed.moments, binned.moments, rtol=1e-12)
    np.testing.assert_array_equal(fixed.hits, binned.hits)  # every sample's, not every D-th
    assert fixed.good.sum() > 0.9 * binned.good.sum()
    assert np.all(np.isfinite(fixed.transfer)) and np.all(np.isfinite(fixed.noise_shaping))
    both = fixed.good & binned.good
    assert not np.allclose(fixed.nosys[1:, both], binned.nosys[1:, both])
    # the sky's polarisation comes through both map-makers alike at the largest scales kept
    assert 0.5 < np.median(fixed.transfer[2, 40:80] / binned.transfer[2, 40:80]) < 2.0
    # the binned map-makers of the pass are unchanged by the calibration's h x CMB row (to
    # the rounding of the single-precision calibration TODs: measured 3e-8)
    for variant, alone in together.items():
        beside = demodulated[variant]
        assert_same(beside, alone, variant)
        np.testing.assert_allclose(beside.transfer, alone.transfer, rtol=0, atol=1e-6)
        assert beside.cmb_h_transfer.size == 0
    assert fixed.cmb_h_transfer.shape == fixed.transfer.shape


def test_demodulated_variants_of_two_resolutions_share_one_demodulation(passes):
    """Two demodulated map-makers (nside 32 and 16) in one pass demodulate each chunk
    once for both: the nside-16 one is what a pass demodulating it alone gives (to
    rounding; the single-precision calibration TODs' spectra to 1e-6)."""
    _, _, _, arguments = passes
    key = (COARSE_NSIDE, 60.0, "demodulated")
    both = fixed_maps.fixed_passes(
        *arguments,
        extra_variants=VARIANTS,
        demodulated_variants=[(SCAN_NSIDE, 60.0), key[:2]],
    )[key]
    alone = fixed_maps.fixed_passes(
        *arguments, extra_variants=VARIANTS, demodulated_variants=[key[:2]]
    )[key]
    assert_same(both, alone, key)
    for name in ("transfer", "noise_shaping", "noise_h_shaping", "cmb_h_transfer"):
        np.testing.assert_allclose(getattr(both, name), getattr(alone, name), rtol=0, atol=1e-6)
