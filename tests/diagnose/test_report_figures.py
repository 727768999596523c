"""The diagnosis figures of a wafer: at most MAX_PANELS detectors, the ones the fit changed."""

import numpy as np

from hwp_tes_systematics.diagnose.report.figures import MAX_PANELS, panel_detectors


def test_every_detector_of_a_pair_is_drawn():
    rng = np.random.default_rng(0)
    before = rng.normal(size=(2, 100))
    assert panel_detectors(before, before, np.ones((2, 100), bool)) == [0, 1]


def test_a_wafer_draws_the_detectors_the_fit_changed_most():
    rng = np.random.default_rng(1)
    n_det = 3 * MAX_PANELS
    after = rng.normal(size=(n_det, 1000))
    before = after.copy()
    changed = [2, 5, 7, 11, 13, 17, 19, 23]
    for rank, k in enumerate(changed):  # a sinusoid the fit removed, stronger each
        before[k] += (1 + rank) * np.sin(np.arange(1000) / 7.0)
    valid = np.ones_like(after, dtype=bool)
    valid[5, :] = False  # a detector with few valid samples changes little
    valid[5, :10] = True
    shown = panel_detectors(before, after, valid)
    assert len(shown) == MAX_PANELS
    assert shown == sorted(shown)
    assert set(shown) >= {2, 7, 11, 13, 17, 19, 23}
    valid[5, :] = False  # none valid: never drawn
    assert 5 not in panel_detectors(before, after, valid)
