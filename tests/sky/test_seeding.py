"""Random streams depend only on (master seed, names)."""

import numpy as np
import pytest

from hwp_tes_systematics.seeding import integer_seed, rng


def test_same_names_same_stream_different_names_different_stream():
    a = rng(7, "noise", "M1-140", 0, "det").normal(size=5)
    b = rng(7, "noise", "M1-140", 0, "det").normal(size=5)
    c = rng(7, "noise", "M1-140", 1, "det").normal(size=5)
    d = rng(8, "noise", "M1-140", 0, "det").normal(size=5)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert not np.allclose(a, d)


def test_order_of_creation_does_not_matter():
    first = [rng(1, "cmb", seed).normal() for seed in range(4)]
    second = [rng(1, "cmb", seed).normal() for seed in reversed(range(4))][::-1]
    assert first == second


def test_integer_seed_is_stable():
    assert integer_seed(1, "x") == integer_seed(1, "x")
    assert integer_seed(1, "x") != integer_seed(1, "y")
    assert 0 <= integer_seed(1, "x") < 2**32


def test_g1_draws_per_detector_or_per_pair():
    from hwp_tes_systematics.analysis.systematics import unit_g1_draws

    detectors = ["det_a", "det_b"]
    per_detector = unit_g1_draws(7, "M1-140", 0, detectors, "detector")
    per_pair = unit_g1_draws(7, "M1-140", 0, detectors, "pair")
    assert per_detector[0] != per_detector[1]
    assert per_pair[0] == per_pair[1]
    np.testing.assert_array_equal(per_pair, unit_g1_draws(7, "M1-140", 0, detectors, "pair"))
    assert unit_g1_draws(7, "M1-140", 1, detectors, "pair")[0] != per_pair[0]
    with pytest.raises(ValueError, match="per"):
        unit_g1_draws(7, "M1-140", 0, detectors, "wafer")
