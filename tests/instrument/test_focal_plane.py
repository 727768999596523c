"""Many detector pairs per channel (instrument.focal_plane, load_channel(pairs=...)).

The layout fills the field of view with one sector per wafer; the choice of N pairs is
nested and spread; a detector placed at theta from the boresight points theta away from a
boresight detector at every sample; and N pairs in one pass bin the same normal equations
as N one-pair passes (the binned map of a channel is the sum of its pairs' equations).
"""

import dataclasses

import numpy as np
import pytest
from helpers import pipeline_settings

from hwp_tes_systematics.analysis.systematics import unit_g1_draws
from hwp_tes_systematics.instrument import InstrumentModelError, load_channel
from hwp_tes_systematics.instrument.channels import pixel_of
from hwp_tes_systematics.instrument.focal_plane import (
    PixelPosition,
    angular_separation_deg,
    choose_pixels,
    lay_out_pixels,
    sunflower_uv_deg,
)
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import accumulate

MFT_FIELD_DEG = (14.0, 14.0)


def test_sunflower_fills_the_ellipse_uniformly():
    uv = sunflower_uv_deg(2000, (9.0, 4.5))
    radius = np.hypot(uv[:, 0] / 9.0, uv[:, 1] / 4.5)
    assert radius.max() <= 1.0
    # uniform in area: the inner half of the area holds half the points
    assert np.mean(radius < np.sqrt(0.5)) == pytest.approx(0.5, abs=0.01)
    assert np.mean(uv[:, 0] > 0) == pytest.approx(0.5, abs=0.02)


def test_each_wafer_holds_one_sector_of_the_field():
    pixels = [f"p{i}" for i in range(90)]
    wafers = ["A"] * 30 + ["B"] * 30 + ["C"] * 30
    layout = lay_out_pixels(pixels, wafers, MFT_FIELD_DEG)
    for wafer in "ABC":
        phi = np.sort(
            [layout[p].phi_deg for p, w in zip(pixels, wafers, strict=True) if w == wafer]
        )
        others = [layout[p].phi_deg for p, w in zip(pixels, wafers, strict=True) if w != wafer]
        # no other wafer's pixel lies inside this wafer's azimuth range (sectors are disjoint)
        inside = [(phi[0] < o < phi[-1]) for o in others]
        assert not any(inside), wafer
    assert max(p.theta_deg for p in layout.values()) <= 14.0


def test_the_choice_of_pairs_is_nested_and_spreads_over_the_field():
    layout = lay_out_pixels([f"p{i}" for i in range(100)], ["A"] * 100, MFT_FIELD_DEG)
    eight = choose_pixels(layout, "p50", 8)
    assert eight[0] == "p50"
    assert choose_pixels(layout, "p50", 4) == eight[:4]
    separations = [
        angular_separation_deg(layout[a], layout[b])
        for i, a in enumerate(eight)
        for b in eight[i + 1 :]
    ]
    # eight points spread over a disc of radius 14 deg: no two closer than a third of it
    assert min(separations) > 14.0 / 3


def test_load_channel_with_n_pairs_keeps_the_default_pair_first():
    one = load_channel("M1-140")
    four = load_channel("M1-140", pairs=4, field_of_view_deg=MFT_FIELD_DEG)
    assert four.detectors[:2] == one.detectors
    assert four.n_pairs == 4 and len(set(four.detectors)) == 8
    for k in range(0, 8, 2):
        assert pixel_of(four.detectors[k]) == pixel_of(four.detectors[k + 1])
        assert four.detector_positions[k] == four.detector_positions[k + 1]
    assert len({pixel_of(name) for name in four.detectors}) == 4
    assert one.detector_positions is None
    assert load_channel("M1-140", pairs=4).detectors == four.detectors  # same choice
    assert load_channel("L1-040", pairs="all").n_pairs == 24  # PTEP: 48 detectors


def test_too_many_pairs_is_a_clear_error():
    with pytest.raises(InstrumentModelError, match="pairs_per_channel = 25 for L1-040.*24 pixels"):
        load_channel("L1-040", pairs=25)


def test_g1_draws_per_detector_pair_and_channel():
    detectors = load_channel("M1-140", pairs=3).detectors
    per_detector = unit_g1_draws(7, "M1-140", 0, detectors, "detector")
    per_pair = unit_g1_draws(7, "M1-140", 0, detectors, "pair")
    per_channel = unit_g1_draws(7, "M1-140", 0, detectors, "channel")
    assert len(set(per_detector)) == 6
    assert len(set(per_pair)) == 3 and np.all(per_pair[::2] == per_pair[1::2])
    assert np.all(per_channel == per_channel[0])
    # with one pair, "pair" and "channel" are the same draw (the paper's g1^i)
    one = detectors[:2]
    np.testing.assert_array_equal(
        unit_g1_draws(7, "M1-140", 0, one, "pair"), unit_g1_draws(7, "M1-140", 0, one, "channel")
    )
    assert per_pair[0] == per_channel[0]


def test_an_emulated_focal_plane_scales_every_g1_draw_by_the_root_of_the_pairs_ratio(
    default_config,
):
    """A channel of N = 3 simulated pairs whose seeds emulate N_e = 183 (M1-140's every
    pair): each unit draw is sqrt(3 / 183) of the seed's own, so that the random
    population's template power, sum_k z_k^2 C_ell(T_k) on average, is that of N_e pairs
    whose shares of the map are N / N_e of these; outside the systematics channels, zeros."""
    import copy

    from hwp_tes_systematics.analysis.channel_alms import channel_g1_draws

    config = copy.deepcopy(default_config)
    config["instrument"]["pairs_per_channel"] = 3
    detectors = load_channel("M1-140", pairs=3).detectors
    own = channel_g1_draws(config, "M1-140", 0, detectors)
    np.testing.assert_array_equal(
        own, unit_g1_draws(config["master_seed"], "M1-140", 0, detectors, "detector")
    )
    config["instrument"]["emulated_pairs_per_channel"] = "all"
    emulated = channel_g1_draws(config, "M1-140", 0, detectors)
    np.testing.assert_allclose(emulated, own * np.sqrt(3 / 183), rtol=1e-14)
    assert not np.any(channel_g1_draws(config, "L1-040", 0, detectors[:2]))


def two_pair_simulator(duration_s, nside, positions):
    channel = load_channel("M1-140", pairs=2)
    channel = dataclasses.replace(channel, detector_positions=positions)
    plan = MissionPlan("2032-04-01T00:00:00", duration_s, duration_s, 19.0)
    return PairSimulator(channel, plan, nside, noise_model="keshner")


def test_a_detector_off_the_boresight_points_that_far_from_it():
    boresight, offset = PixelPosition(0.0, 0.0), PixelPosition(7.0, 40.0)
    simulator = two_pair_simulator(600.0, 16, (boresight, boresight, offset, offset))
    pointing = simulator.pointing(0, 600 * 19)
    assert pointing.galactic_rad.shape[0] == 2  # one direction per pixel
    np.testing.assert_array_equal(pointing.direction_of, [0, 0, 1, 1])
    theta, phi = pointing.galactic_rad[..., 0], pointing.galactic_rad[..., 1]
    vectors = np.stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1
    )
    separation_deg = np.degrees(np.arccos(np.sum(vectors[0] * vectors[1], axis=-1)))
    np.testing.assert_allclose(separation_deg, 7.0, atol=1e-6)
    np.testing.assert_array_equal(pointing.pixels[0], pointing.pixels[1])
    assert np.mean(pointing.pixels[0] != pointing.pixels[2]) > 0.9


@pytest.mark.slow
def test_n_pairs_in_one_pass_bin_the_sum_of_the_one_pair_passes():
    """The channel's normal equations with two pairs (each at its own position) are the
    sums of each pair's own, template rows per detector included, to round-off."""
    positions = (PixelPosition(3.0, 10.0),) * 2 + (PixelPosition(9.0, 200.0),) * 2
    both = two_pair_simulator(3 * 3600.0, 16, positions)
    settings = dataclasses.replace(pipeline_settings(both, noise_scale=0.0), notch_margin_s=600.0)
    sky = np.zeros((3, 12 * 16**2))
    sky[0] = 1e-4 * np.cos(np.arange(sky.shape[1]))
    together = accumulate(both, settings, sky)
    alone = []
    for k in (0, 2):
        pair = dataclasses.replace(
            both.channel,
            detectors=both.channel.detectors[k : k + 2],
            detector_positions=positions[k : k + 2],
        )
        alone.append(
            accumulate(PairSimulator(pair, both.plan, 16, noise_model="keshner"), settings, sky)
        )
    summed = alone[0].pixel_matrix + alone[1].pixel_matrix
    np.testing.assert_allclose(
        together.pixel_matrix, summed, rtol=0, atol=1e-12 * np.abs(summed).max()
    )
    np.testing.assert_array_equal(together.hits, alone[0].hits + alone[1].hits)
    scale = np.abs(together.pixel_rhs).max(axis=(0, 2))
    np.testing.assert_allclose(
        together.pixel_rhs[:, 0],
        alone[0].pixel_rhs[:, 0] + alone[1].pixel_rhs[:, 0],
        rtol=0,
        atol=1e-10 * scale[0],
    )
    for term in range(3):  # rows 1 + term n_det + k: detector k's term
        for k in range(4):
            pair, local = divmod(k, 2)
            np.testing.assert_allclose(
                together.pixel_rhs[:, 1 + 4 * term + k],
                alone[pair].pixel_rhs[:, 1 + 2 * term + local],
                rtol=0,
                atol=1e-10 * scale[1 + 4 * term + k],
            )


def test_a_focal_plane_too_large_for_memory_is_refused_before_the_first_chunk(monkeypatch):
    from collections import namedtuple

    from hwp_tes_systematics.simulation import tod_maps

    simulator = two_pair_simulator(86400.0, 16, None)
    settings = pipeline_settings(simulator)
    needed = tod_maps.chunk_memory_bytes(4, settings)
    assert 1.5e9 < needed < 3e9  # 4 detectors, one 19 Hz day with 1200 s margins
    memory = namedtuple("memory", "available")
    monkeypatch.setattr(tod_maps.psutil, "virtual_memory", lambda: memory(needed + 1))
    tod_maps.check_chunk_memory(simulator, settings)
    monkeypatch.setattr(tod_maps.psutil, "virtual_memory", lambda: memory(needed - 1))
    with pytest.raises(MemoryError, match="pairs_per_channel.*chunk_duration_s"):
        tod_maps.accumulate(simulator, settings, np.zeros((3, 12 * 16**2)))
