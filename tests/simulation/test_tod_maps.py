"""TOD simulation and binned maps: litebird_sim agreement, linearity in g1, chunking."""

import healpy as hp
import numpy as np
import pytest
from helpers import m1_140_pair

from hwp_tes_systematics.simulation.mapmaking import NormalEquations, solve_maps
from hwp_tes_systematics.simulation.tod_maps import (
    PairMapSettings,
    accumulate,
    detector_weights,
    split_solved_maps,
)

NSIDE = 16


@pytest.fixture(scope="module")
def simulator():
    return m1_140_pair(3600.0, 1800.0, NSIDE)


def settings_for(simulator, seed=0, a2_k_cmb=0.3):
    return PairMapSettings(
        master_seed=11,
        seed=seed,
        nside=NSIDE,
        plan=simulator.plan,
        a2_k_cmb=a2_k_cmb,
        notch_width_divisor=100.0,
        notch_margin_s=300.0,
        max_condition_number=100.0,
    )


def random_sky(seed=0):
    return np.random.default_rng(seed).normal(size=(3, hp.nside2npix(NSIDE))) * 1e-4


@pytest.mark.slow
def test_scan_matches_litebird_sim_scan_map(simulator):
    import litebird_sim as lbs

    pointing = simulator.pointing(0, 20_000)
    sky = random_sky()
    ours = simulator.scan_sky(pointing, sky)
    observation = pointing.observation
    observation.tod[:] = 0.0
    lbs.scan_map_in_observations(
        observation,
        maps=lbs.HealpixMap(values=sky, nside=NSIDE, coordinates=lbs.CoordinateSystem.Galactic),
        hwp=lbs.IdealHWP(simulator.hwp_rad_per_s),
    )
    np.testing.assert_allclose(ours, observation.tod, atol=1e-12)


@pytest.mark.slow
def test_pointing_and_dipole_equal_litebird_sim(simulator):
    """The pointing (ducc0's quaternions, our angle kernel) equals litebird_sim's ecliptic
    pointing rotated to Galactic, and the dipole from the direction vectors equals
    litebird_sim's add_dipole on those angles, both to rounding."""
    import litebird_sim as lbs

    pointing = simulator.pointing(1000, 20_000)
    galactic = lbs.rotate_coordinates_e2g(np.ascontiguousarray(pointing.ecliptic_rad()[0]))
    difference = pointing.galactic_rad[0] - galactic
    difference[:, 1:] = (difference[:, 1:] + np.pi) % (2 * np.pi) - np.pi  # phi, psi wrap
    assert np.abs(difference).max() < 1e-10
    vectors = hp.ang2vec(galactic[:, 0], galactic[:, 1])
    np.testing.assert_allclose(pointing.galactic_vectors[0], vectors, rtol=0, atol=1e-12)
    observation = pointing.observation
    observation.tod[:] = 0.0
    lbs.add_dipole_to_observations(
        observation,
        pos_and_vel=simulator.orbit_galactic,
        pointings=pointing.galactic_rad[pointing.direction_of],
    )
    ours = simulator.dipole(pointing)
    assert np.abs(ours).max() > 1e-3  # the orbital + solar dipole, a few mK
    np.testing.assert_allclose(ours, observation.tod, rtol=0, atol=1e-12 * np.abs(ours).max())


@pytest.mark.slow
def test_binned_qu_equal_input_with_hwp(simulator):
    """litebird_sim #498 (binned Q/U a factor 2 off with a HWP) must not happen here."""
    import litebird_sim as lbs

    sky = random_sky(1)
    pointing = simulator.pointing(0, simulator.plan.n_samples)
    tod = simulator.scan_sky(pointing, sky)
    equations = NormalEquations(NSIDE, 1)
    equations.add(
        pointing.pixels,
        pointing.cos_2alpha,
        pointing.sin_2alpha,
        detector_weights(simulator),
        simulator.pol_efficiency,
        [tod],
    )
    maps, condition, good = solve_maps(equations, 100.0)
    assert good.sum() > 100
    assert np.abs(maps[0][:, good] - sky[:, good]).max() < 1e-6 * np.abs(sky).max()
    # and the same as litebird_sim's own binner on the same samples
    observation = pointing.observation
    observation.tod[:] = tod
    reference = lbs.make_binned_map(NSIDE, observation, hwp=lbs.IdealHWP(simulator.hwp_rad_per_s))
    np.testing.assert_allclose(maps[0][:, good], reference.binned_map[:, good], rtol=0, atol=1e-12)
    assert np.median(condition[good]) == pytest.approx(2.0, rel=0.05)


@pytest.mark.slow
def test_maps_are_linear_in_g1(simulator):
    """m_nosys + sum_k g1_k T_k equals the map of a TOD with g1 injected, to 1e-10."""
    settings = settings_for(simulator)
    sky = random_sky(2)
    linear, _, good = solve_maps(accumulate(simulator, settings, sky), 100.0)
    g1_per_k = np.array([0.05, -0.03])
    direct, _, _ = solve_maps(accumulate(simulator, settings, sky, g1_per_k=g1_per_k), 100.0)
    templates = split_solved_maps(linear, 2, settings.a2_k_cmb)["templates"]
    combined = linear[0] + g1_per_k[0] * templates[0] + g1_per_k[1] * templates[1]
    error = np.abs(combined[:, good] - direct[0][:, good]).max()
    assert error < 1e-10 * np.abs(direct[0][:, good]).max()
    assert np.abs(templates[0][:, good]).max() > 0  # the templates are not empty


@pytest.mark.slow
def test_chunks_join_up(simulator):
    whole = simulator.pointing(0, 4000)
    part = simulator.pointing(2500, 1000)
    np.testing.assert_array_equal(part.pixels, whole.pixels[:, 2500:3500])
    np.testing.assert_allclose(part.hwp_angle_rad, whole.hwp_angle_rad[2500:3500], atol=1e-9)
    # the spin-axis quaternions are interpolated on a 2 s grid that starts at each chunk's
    # start: orientations agree to the interpolation error (~1 arcsec), not to rounding
    np.testing.assert_allclose(part.cos_2alpha, whole.cos_2alpha[:, 2500:3500], atol=1e-5)


@pytest.mark.slow
def test_same_seed_identical_other_seed_different(simulator):
    sky = random_sky(3)
    first = solve_maps(accumulate(simulator, settings_for(simulator, seed=4), sky), 100.0)[0]
    again = solve_maps(accumulate(simulator, settings_for(simulator, seed=4), sky), 100.0)[0]
    other = solve_maps(accumulate(simulator, settings_for(simulator, seed=5), sky), 100.0)[0]
    np.testing.assert_array_equal(first, again)
    seen = first[0, 0] != hp.UNSEEN
    assert not np.allclose(first[0][:, seen], other[0][:, seen])


@pytest.mark.slow
def test_without_a_notch_the_4f_harmonic_template_removes_the_line(simulator):
    """config/keep_sky.yaml: no notch (notch.width_divisor null), the 4 f_HWP line
    g1 A_2^2 / 2 cos(4 chi) removed as an HWP harmonic template: the line goes, the sky
    passes untouched (no filter at all without templates)."""
    from hwp_tes_systematics.simulation.tod_filter import notch_with_margins

    settings = settings_for(simulator)
    settings.notch_width_divisor = None
    pointing = simulator.pointing(0, simulator.plan.n_samples)
    sky = simulator.scan_sky(pointing, random_sky(2))  # (2 detectors, samples)
    settings.removed_hwp_harmonics = ()
    np.testing.assert_array_equal(notch_with_margins(sky, pointing, simulator, settings), sky)
    line = 1e-4 * np.cos(4 * pointing.hwp_angle_rad + 0.3) * np.ones((2, 1))
    settings.removed_hwp_harmonics = (2,)
    np.testing.assert_allclose(
        notch_with_margins(line, pointing, simulator, settings), line, atol=1e-6
    )
    settings.removed_hwp_harmonics = (2, 4)
    cleaned = notch_with_margins(line, pointing, simulator, settings)
    assert np.abs(cleaned).max() < 1e-12


def test_a_chunk_stride_keeps_every_nth_chunk_of_the_mission():
    """simulation.chunk_stride: the chunks simulated are the mission's own, of index
    divisible by the stride, at their own first samples; a stride below 1 is refused."""
    from hwp_tes_systematics.simulation.tod import MissionPlan

    whole = MissionPlan("2032-04-01T00:00:00", 10 * 3600.0, 3600.0, 19.0)
    sampled = MissionPlan("2032-04-01T00:00:00", 10 * 3600.0, 3600.0, 19.0, chunk_stride=4)
    assert sampled.chunks() == [chunk for chunk in whole.chunks() if chunk[0] % 4 == 0]
    assert [index for index, _, _ in sampled.chunks()] == [0, 4, 8]
    assert sampled.simulated_samples == 3 * 3600 * 19 and sampled.n_samples == whole.n_samples
    for stride in (0, 1.5):
        with pytest.raises(ValueError, match="chunk_stride"):
            MissionPlan("2032-04-01T00:00:00", 3600.0, 600.0, 19.0, chunk_stride=stride)


@pytest.mark.slow
def test_a_sampled_mission_bins_the_samples_of_its_chunks_only():
    """A pass with chunk_stride 2 over four chunks hits exactly the pixels of chunks 0
    and 2 of the whole mission (each chunk at its own time and pointing)."""
    import dataclasses

    simulator = m1_140_pair(4 * 1800.0, 1800.0, 16, 19.0, noise_model="keshner")
    plan = dataclasses.replace(simulator.plan, chunk_stride=2)
    settings = dataclasses.replace(settings_for(simulator), plan=plan)
    equations = accumulate(simulator, settings, random_sky(5))
    expected = np.zeros(hp.nside2npix(16))
    for _, first, n_samples in plan.chunks():
        pixels = simulator.pointing(first, n_samples).pixels
        expected += np.bincount(pixels.ravel(), minlength=expected.size)
    np.testing.assert_array_equal(equations.hits, expected)
    assert 0 < expected.sum() == 2 * plan.samples_per_chunk * simulator.n_detectors
