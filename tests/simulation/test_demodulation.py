"""HWP demodulation plus a low-pass (the map-maker beside the binned solve): the
demodulated streams of a modulated signal, a noise-free polarised sky recovered, and
the offset leakage of the binned solve absent."""

import healpy as hp
import numpy as np
import pytest
from helpers import m1_140_pair

from hwp_tes_systematics.simulation.demodulation import (
    DemodulatedEquations,
    demodulate,
    lowpass_transfer,
)
from hwp_tes_systematics.simulation.mapmaking import NormalEquations, solve_maps
from hwp_tes_systematics.simulation.notch import chunk_span
from hwp_tes_systematics.simulation.tod_maps import (
    PairMapSettings,
    accumulate,
    detector_weights,
    split_solved_maps,
)

NSIDE = 16


def test_demodulated_streams_of_a_modulated_signal():
    """d = I + rho (Q cos(4 chi + beta) + U sin(4 chi + beta)) + offset gives
    (I + offset, rho (Q c + U s), rho (U c - Q s)) away from the edges."""
    rate_hz, f_hwp_hz = 19.0, 0.65
    t = np.arange(20000) / rate_hz
    chi = 2 * np.pi * f_hwp_hz * t
    beta = 0.3 + 0.002 * t  # a slowly turning polarisation angle
    i_k, q_k, u_k, rho, offset_k = 2.0, 0.7, -0.4, 0.9, 5.0
    tod = i_k + offset_k + rho * (q_k * np.cos(4 * chi + beta) + u_k * np.sin(4 * chi + beta))
    streams = demodulate(tod, chi, rate_hz, f_hwp_hz)
    middle = slice(2000, -2000)
    expected = [
        np.full(t.size, i_k + offset_k),
        rho * (q_k * np.cos(beta) + u_k * np.sin(beta)),
        rho * (u_k * np.cos(beta) - q_k * np.sin(beta)),
    ]
    for stream, want in zip(streams, expected, strict=True):
        np.testing.assert_allclose(stream[middle], want[middle], atol=2e-3)
    assert lowpass_transfer([0.0, 0.6, 0.65, 0.7], 0.6175, 0.0325).tolist()[::3] == [1.0, 0.0]


@pytest.fixture(scope="module")
def pair():
    return m1_140_pair(3 * 3600.0, 3 * 3600.0, NSIDE)


def noiseless_settings(pair, baseline_length_s):
    """The pair's map-making settings without noise, A_2 = 0.1 K, the paper's notch."""
    return PairMapSettings(
        master_seed=1,
        seed=0,
        nside=NSIDE,
        plan=pair.plan,
        a2_k_cmb=0.1,
        notch_width_divisor=100.0,
        notch_margin_s=300.0,
        max_condition_number=100.0,
        noise_scale=0.0,
        baseline_length_s=baseline_length_s,
    )


def demodulated_map(pair, sky):
    """Scan ``sky`` over the pair's three hours, demodulate, low-pass, bin: (maps, seen)."""
    rate = pair.plan.sampling_rate_hz
    start, n_simulated, inner = chunk_span(0, pair.plan.n_samples, rate, 300.0)
    pointing = pair.pointing(start, n_simulated)
    tod = pair.scan_sky(pointing, sky)
    streams = demodulate(tod, pointing.hwp_angle_rad, rate, pair.channel.hwp_frequency_hz)
    equations = DemodulatedEquations(NSIDE, 1)
    equations.add(
        pointing.pixels[:, inner],
        pointing.cos_2alpha[:, inner],
        pointing.sin_2alpha[:, inner],
        pointing.hwp_angle_rad[inner],
        detector_weights(pair),
        pair.pol_efficiency,
        [streams[..., inner]],
    )
    binned = NormalEquations(NSIDE, 1)
    binned.add(
        pointing.pixels[:, inner],
        pointing.cos_2alpha[:, inner],
        pointing.sin_2alpha[:, inner],
        detector_weights(pair),
        pair.pol_efficiency,
        [tod[:, inner]],
    )
    binned_maps, _, good = solve_maps(binned, 100.0)
    return equations.solve()[0], equations.hits > 0, binned_maps[0], good


@pytest.mark.slow
def test_demodulation_recovers_a_noise_free_polarised_sky(pair):
    """A uniform polarised sky comes back exactly (the algebra of the module docstring);
    a smooth one (20 deg FWHM) within 4 % rms of its Q/U (measured 1.6 %: the TOD of
    a pixelized sky steps at pixel edges and the low-pass smooths the steps, which the
    binned solve, exact on the same TOD, does not see)."""
    npix = hp.nside2npix(NSIDE)
    uniform = np.array([3.0, 0.7, -0.4])[:, None] * np.ones(npix) * 1e-6
    maps, seen, _, _ = demodulated_map(pair, uniform)
    assert seen.mean() > 0.02
    np.testing.assert_allclose(maps[:, seen], uniform[:, seen], rtol=1e-6)
    lmax = 3 * NSIDE - 1
    rng = np.random.default_rng(7)
    alm = rng.normal(size=(3, hp.Alm.getsize(lmax)), scale=1e-6) * (1 + 0j)
    smooth = hp.alm2map(alm, NSIDE, lmax=lmax, fwhm=np.radians(20.0))
    maps, seen, binned, good = demodulated_map(pair, smooth)
    error = maps[1:, seen] - smooth[1:, seen]
    relative = np.sqrt(np.mean(error**2) / np.mean(smooth[1:, seen] ** 2))
    print(f"smooth polarised sky: Q/U error {relative:.2%} rms")
    assert relative < 0.04, relative
    np.testing.assert_allclose(binned[1:, good], smooth[1:, good], atol=1e-12)


@pytest.mark.slow
def test_demodulation_removes_the_offset_leakage_of_the_binned_solve(pair):
    """On the paper-literal path (no baselines) the h^2 term of the nonlinearity
    (a per-detector DC term A_2^2 / 2 and a 4f line) leaks into the binned Q/U through
    the HWP-angle coverage; the demodulated maps of the same filtered TODs hold < 1e-4 of it (measured
    1.7e-8 against 9.6e-3 K^2 per unit A_2^2, on the pixels both see)."""
    settings = noiseless_settings(pair, baseline_length_s=None)
    demodulated = DemodulatedEquations(NSIDE, 1 + 3 * pair.n_detectors)
    equations = accumulate(
        pair, settings, np.zeros((3, hp.nside2npix(NSIDE))), demodulated=demodulated
    )
    binned, _, good = solve_maps(equations, 100.0)
    binned_hh = split_solved_maps(binned, pair.n_detectors, 0.1)["template_terms"][2]
    demodulated_hh = split_solved_maps(demodulated.solve(), pair.n_detectors, 0.1)[
        "template_terms"
    ][2]
    both = good & (demodulated.hits > 0)  # the pixels both map-makers saw
    binned_rms = np.sqrt(np.mean(binned_hh[:, 1:, both] ** 2))
    demodulated_rms = np.sqrt(np.mean(demodulated_hh[:, 1:, both] ** 2))
    print(f"h^2 term Q/U rms: binned {binned_rms:.2g}, demodulated {demodulated_rms:.2g}")
    assert binned_rms > 1e-3, binned_rms  # per-cent leakage of the 0.5 DC term
    assert demodulated_rms < 1e-4 * binned_rms, (demodulated_rms, binned_rms)


@pytest.mark.slow
@pytest.mark.parametrize("baseline_length_s", [None, 60.0])
def test_a_demodulated_extra_binning_is_the_demodulated_map_maker(pair, baseline_length_s):
    """The fixed pass's demodulated map-maker (an ExtraBinning beside the binned one, with
    the calibration TODs) bins the same demodulated streams as ``accumulate(...,
    demodulated=)``: equal maps to rounding; its white-noise equations hold the binned
    solve's M."""
    from hwp_tes_systematics.simulation.chunk_binning import ExtraBinning
    from hwp_tes_systematics.simulation.tod_maps import Calibration

    npix = hp.nside2npix(NSIDE)
    rng = np.random.default_rng(3)
    sky = rng.normal(size=(3, npix)) * 1e-5
    settings = noiseless_settings(pair, baseline_length_s)
    n_tods = 1 + 3 * pair.n_detectors
    reference = DemodulatedEquations(NSIDE, n_tods)
    direct = accumulate(pair, settings, sky, demodulated=reference)
    extra = ExtraBinning(NSIDE, baseline_length_s, demodulated=True)
    calibration = Calibration(NSIDE, (sky,), 77, hwpss_noise=True)
    beside = accumulate(pair, settings, sky, calibration=calibration, extra_binnings=(extra,))
    np.testing.assert_allclose(extra.equations.solve(), reference.solve(), rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(extra.equations.hits, reference.hits)
    np.testing.assert_allclose(extra.matrix_equations.matrix, direct.matrix, rtol=1e-12)
    np.testing.assert_allclose(beside.matrix, direct.matrix, rtol=1e-12)
    assert extra.calibration_equations.n_tods == 1 + calibration.n_noise_tods  # filtered
    np.testing.assert_array_equal(extra.calibration_equations.hits, reference.hits)
    assert extra.white_equations.n_tods == calibration.n_noise_tods
    assert np.all(extra.white_equations.hits == extra.matrix_equations.hits)


@pytest.mark.slow
def test_a_band_limited_sky_leaves_no_hwpss_product_in_the_demodulated_streams(pair):
    """The 2 f_HWP HWPSS times a sky TOD, demodulated: a nearest-pixel scan steps at each
    pixel crossing, and the steps' power near 2 f_HWP reaches the streams (measured 2.4 %
    of the sky TOD's rms here, 3.5 % at nside 32); the same sky scanned band-limited
    leaves 4.6e-7 of it. Asserted: > 1 % and < 1e-4."""
    from hwp_tes_systematics import sky
    from hwp_tes_systematics.sky.harmonics import BandLimitedSky

    lmax = 3 * NSIDE - 1
    alm = sky.smooth_alm(sky.cmb_alm(lmax, 0.0, 7, 0), 30.0, lmax)
    pointing = pair.pointing(0, pair.plan.n_samples)
    hwpss = pair.hwpss(pointing, 1.0)
    f_hwp_hz = pair.channel.hwp_frequency_hz
    leaked = {}
    for name, scanned in (
        ("nearest", hp.alm2map(alm, NSIDE, lmax=lmax, pixwin=False)),
        ("band-limited", BandLimitedSky(alm, lmax)),
    ):
        tod = pair.scan_sky(pointing, scanned)[0]
        streams = demodulate(
            tod * hwpss[0], pointing.hwp_angle_rad, pair.plan.sampling_rate_hz, f_hwp_hz
        )
        middle = streams[:, 3000:-3000]  # away from the low-pass's wrap-around
        leaked[name] = np.sqrt(np.mean(middle**2)) / np.std(tod)
    assert leaked["nearest"] > 1e-2, leaked
    assert leaked["band-limited"] < 1e-4, leaked


def test_decimated_demodulation_is_the_demodulation_at_every_dth_sample():
    """demodulate(decimation=D) with D = decimation_factor (7 at 19 Hz, f_HWP 0.65 Hz):
    the full-rate streams at samples 0, D, 2 D, ... to 1e-6 of their amplitude 1,200 s
    from the ends (the low-pass's wrap-around differs with the padded length: measured
    1e-7); a stride beyond the low-pass's Nyquist limit is refused."""
    from hwp_tes_systematics.simulation.demodulation import decimation_factor

    rate_hz, f_hwp_hz = 19.0, 0.65
    n = 100_003
    chi = 2 * np.pi * f_hwp_hz * np.arange(n) / rate_hz + 0.3
    tod = np.random.default_rng(1).normal(size=(2, n))
    stride = decimation_factor(rate_hz, f_hwp_hz)
    assert stride == 7
    full = demodulate(tod, chi, rate_hz, f_hwp_hz)[..., ::stride]
    decimated = demodulate(tod, chi, rate_hz, f_hwp_hz, decimation=stride)
    assert decimated.shape == full.shape
    edge = int(1200 * rate_hz) // stride
    difference = np.abs(decimated - full)[..., edge:-edge].max()
    assert difference < 1e-6 * np.abs(full).max(), difference
    with pytest.raises(ValueError, match="decimated Nyquist"):
        demodulate(tod, chi, rate_hz, f_hwp_hz, decimation=20)
