"""Two effects near the selection's threshold (issue 29): a 4f HWPSS of 40 uK and a TES
nonlinearity g1 = -2e-3 (70 uK of 4f line, 2f +- f_spin sidebands of ~1.8 uK) in a 6 h
M1-140 pair. The BIC keeps the 4f line; the nonlinearity, whose own signature (the
sidebands) cannot pay for it at this depth, must still be named as what the line may be."""

import numpy as np
import pytest

from hwp_tes_systematics.diagnose.testbed import recorded, run

pytestmark = pytest.mark.slow


def test_the_weaker_member_of_a_pair_is_named_as_a_look_alike(tmp_path):
    phase = 1.1  # rad, of the 4f HWPSS harmonic
    effects = [
        ("tes_nonlinearity", {"g1": -2e-3}),
        ("hwpss_harmonics", {"c4": 40e-6 * np.cos(phase), "s4": 40e-6 * np.sin(phase)}),
    ]
    recording, _ = recorded(tmp_path, effects, 7301, hours=6.0)
    result = run(recording, figures=False)
    named = set(result.effect_names)
    for effect in result["effects"]:
        named |= set(effect["look_alikes"])
    assert {"hwpss_harmonics", "tes_nonlinearity"} <= named, result["effects"]
    assert result["unexplained"] == []


def test_an_unphysical_coupling_is_not_reported_as_physics(tmp_path):
    """An HWP intensity-to-2f coupling of 0.3 (beyond the catalog's physical bound 0.1) is
    not reported as hwpss_intensity_coupling, nor is the nonlinearity of g1 ~0.6 K^-1 the
    selection would otherwise take in its place: the 2 f_HWP +- f_spin sidebands it makes
    are left in ``unexplained``. A coupling of 0.02 is found as itself."""
    recording, _ = recorded(tmp_path, [("hwpss_intensity_coupling", {"a2c": 0.02})], 9100)
    assert run(recording, figures=False).effect_names == ["hwpss_intensity_coupling"]
    recording, _ = recorded(tmp_path, [("hwpss_intensity_coupling", {"a2c": 0.3})], 9100)
    result = run(recording, figures=False)
    assert "hwpss_intensity_coupling" not in result.effect_names
    assert not {"tes_nonlinearity", "tes_nonlinearity_cubic"} & set(result.effect_names)
    texts = " ".join(entry["text"] for entry in result["unexplained"])
    assert "2 f_HWP - f_spin" in texts and "2 f_HWP + f_spin" in texts
    for entry in result["unexplained"]:  # each detector named once per structure
        assert len(set(entry["detectors"])) == len(entry["detectors"]), entry["text"]
    removed = [s for s in result["steps"] if "outside physical bounds" in (s.get("note") or "")]
    assert removed, "the selection says what it removed and why"
