"""Recordings longer than memory allows are diagnosed segment by segment (issue 29, item 7):
the segments fit the budget and cover the recording, a segment read from the file is that
stretch of the whole, and the combination of the segments' findings is the
inverse-variance mean with a consistency check; on a recording, the segmented diagnosis
finds what the whole one finds."""

import itertools
import json

import numpy as np
import pytest

from hwp_tes_systematics.diagnose import RecordingError, read_recording
from hwp_tes_systematics.diagnose.bound.requirement_check import load_requirement
from hwp_tes_systematics.diagnose.effects.event_groups import Coincidences, coincidence_scope
from hwp_tes_systematics.diagnose.effects.step_search import StepEvent
from hwp_tes_systematics.diagnose.recording_checks import diagnosis_memory_bytes
from hwp_tes_systematics.diagnose.report.diagnosis import scope_lines
from hwp_tes_systematics.diagnose.segments import (
    VARIES_P,
    combine_segments,
    diagnose_segments,
    plan_segments,
)
from hwp_tes_systematics.diagnose.testbed import A2_K, recorded, run, sky_map

RATE_HZ = 19.0
WEEK = int(7 * 86400 * RATE_HZ)


def test_a_week_is_cut_into_the_fewest_equal_segments_that_fit_the_budget():
    budget = 16 * 2**30
    bounds = plan_segments(WEEK, 2, RATE_HZ, budget)
    lengths = np.diff(np.array(bounds), axis=1).ravel()
    assert bounds[0][0] == 0 and bounds[-1][1] == WEEK
    assert all(a[1] == b[0] for a, b in itertools.pairwise(bounds))
    assert lengths.max() - lengths.min() <= 1
    assert all(diagnosis_memory_bytes(2, n) <= budget for n in lengths)
    one_fewer = WEEK / (len(bounds) - 1)  # fewer segments would not fit
    assert diagnosis_memory_bytes(2, one_fewer) > budget
    # a requested length is honoured when the budget allows it
    daily = plan_segments(WEEK, 2, RATE_HZ, budget, segment_hours=24)
    assert len(daily) == 7


def test_a_budget_too_small_for_an_hour_is_an_error_naming_the_file():
    with pytest.raises(RecordingError, match=r"week.h5: a memory budget of .* less than the 1 h"):
        plan_segments(WEEK, 2, RATE_HZ, 0.8 * 2**30, source="week.h5")  # 0.9 h


def entry(value, sigma, parameter="g1", unit="1/K", detector="d0"):
    return {
        "value": value,
        "sigma": sigma,
        "unit": unit,
        "detector": detector,
        "parameter": parameter,
    }


def segment_result(g1, sigma, glitch_time_s=None, unexplained=()):
    effects = [
        {
            "name": "tes_nonlinearity",
            "title": "TES nonlinearity",
            "signature": "s",
            "main_parameters": ["g1"],
            "parameters": {"g1[d0]": entry(g1, sigma)},
            "delta_chi2": 100.0,
            "delta_bic": -90.0,
            "evidence": "e",
            "look_alikes": [],
        }
    ]
    if glitch_time_s is not None:
        effects.append(
            {
                **effects[0],
                "name": "glitches",
                "parameters": {"glitch0.time[d0]": entry(glitch_time_s, 0.1, "time", "s")},
                "delta_chi2": 50.0,
            }
        )
    return {
        "mismatch_found": True,
        "effects": effects,
        "unexplained": [{"kind": "line", "text": text} for text in unexplained],
        "nominal_adjustments": {"d0": {"gain": {**entry(1.0, 0.01, "gain", ""), "nominal": 1.0}}},
        "chi2_before": 200.0,
        "chi2_after": 100.0,
        "bic_before": 210.0,
        "bic_after": 120.0,
        "dof": 90,
        "n_eff": 100,
        "delta_bic_threshold": -10.0,
        "information_criterion": "BIC",
        "steps": [{"step": 1, "note": "n"}],
        "lines": [{"identification": "4f"}],
        "noise": {"nominal": [{"net_k_sqrt_s": 1.0}], "estimated": [{"net_k_sqrt_s": 1.0}]},
        "recording": {"duration_s": 3600.0, "flagged_fraction": 0.0, "source": "r.h5"},
    }


REQUIREMENT = load_requirement()  # the shipped one-year result


def test_parameters_combine_as_the_inverse_variance_mean_and_events_stay_per_segment():
    results = [
        segment_result(-3.0e-3, 1e-4, glitch_time_s=100.0),
        segment_result(-3.2e-3, 2e-4, unexplained=["a line"]),
    ]
    combined = combine_segments(results, [(0, 3600), (3600, 7200)], 1.0, REQUIREMENT)
    nonlinearity = next(e for e in combined["effects"] if e["name"] == "tes_nonlinearity")
    g1 = nonlinearity["parameters"]["g1[d0]"]
    weights = np.array([1e-4, 2e-4]) ** -2.0
    assert g1["value"] == pytest.approx(np.sum(weights * [-3.0e-3, -3.2e-3]) / weights.sum())
    assert g1["sigma"] == pytest.approx(weights.sum() ** -0.5)
    assert g1["consistency_dof"] == 1 and not g1["varies_between_segments"]
    assert "sigma_scaled" not in g1
    assert [s["value"] for s in g1["per_segment"]] == [-3.0e-3, -3.2e-3]
    assert nonlinearity["segments"] == [0, 1] and nonlinearity["delta_chi2"] == 200.0
    glitches = next(e for e in combined["effects"] if e["name"] == "glitches")
    assert glitches["segments"] == [0]
    assert glitches["parameters"]["segment0.glitch0.time[d0]"]["value"] == 100.0
    assert combined["unexplained"][0]["segment"] == 1
    assert combined["unexplained"][0]["text"].startswith("segment 1 (from 1 h)")
    assert combined["chi2_after"] == 200.0 and combined["dof"] == 180
    assert combined["recording"]["duration_s"] == 7200.0
    assert combined["requirement_check"]["effect"] == "tes_nonlinearity"
    json.dumps(combined)  # what diagnosis.json holds


def test_an_effects_scope_is_kept_where_the_segments_agree_and_given_per_segment_where_not():
    wafers = {"by": "wafer", "groups": {"W0": ["d0"], "W1": ["d1"]}}
    results = [segment_result(-3.0e-3, 1e-4), segment_result(-3.1e-3, 1e-4)]
    for result in results:
        result["effects"][0] |= {"scope": wafers, "members": ["tes_nonlinearity"]}
    combined = combine_segments(results, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    assert combined["effects"][0]["scope"] == wafers
    assert combined["effects"][0]["members"] == ["tes_nonlinearity"]
    results[1]["effects"][0]["scope"] = {"by": "detector", "groups": {}}
    combined = combine_segments(results, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    assert "scope" not in combined["effects"][0]
    assert combined["effects"][0]["scope_per_segment"] == {
        0: wafers,
        1: {"by": "detector", "groups": {}},
    }
    lines = scope_lines(json.loads(json.dumps(combined["effects"][0])), 2)  # as read back
    assert lines[0].startswith("*Scope in segment 0*: one set of parameters per wafer")
    assert lines[2].startswith("*Scope in segment 1*: each of the 2 detectors")


def test_a_coincidence_scope_given_per_segment_counts_its_times_from_the_recordings_start():
    found = Coincidences([[0, 1]], [{0, 1}], 1, 1e-3, 1e-3)
    events = [StepEvent(0, 100.0, 1e-4, 0.0), StepEvent(1, 100.0, 1e-4, 0.0)]
    scope = coincidence_scope(found, events, ["d0", "d1"])
    assert scope["groups"] == {"t = 100.00 s": ["d0", "d1"]}  # from the segment's start
    results = [segment_result(-3.0e-3, 1e-4), segment_result(-3.1e-3, 1e-4)]
    results[0]["effects"][0]["scope"] = {"by": "detector", "groups": {}}
    results[1]["effects"][0]["scope"] = scope
    combined = combine_segments(results, [(0, 3600), (3600, 7200)], 1.0, REQUIREMENT)
    second = combined["effects"][0]["scope_per_segment"][1]
    assert second["groups"] == {"t = 3700.00 s": ["d0", "d1"]}
    assert second["times_s"] == [3700.0]


def test_a_parameter_that_changes_between_segments_is_marked():
    results = [segment_result(-3.0e-3, 1e-5), segment_result(-4.0e-3, 1e-5)]
    combined = combine_segments(results, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    g1 = combined["effects"][0]["parameters"]["g1[d0]"]
    assert g1["consistency_p"] < VARIES_P and g1["varies_between_segments"]
    scale = np.sqrt(g1["consistency_chi2"] / g1["consistency_dof"])
    assert g1["sigma_scaled"] == pytest.approx(g1["sigma"] * scale) and scale > 10
    assert combined["effects"][0]["varies_between_segments"] == ["g1[d0]"]
    assert "differ between segments" in combined["effects"][0]["evidence"]


def test_a_segment_read_from_the_file_is_that_stretch_of_it(tmp_path):
    recording, _ = recorded(tmp_path, [], 7001, hours=0.5)
    path = tmp_path / "rec.h5"
    start, stop = 5000, 20000
    segment = read_recording(path, samples=(start, stop))
    np.testing.assert_array_equal(segment.tod, recording.tod[:, start:stop])
    np.testing.assert_array_equal(segment.pointings_ecl, recording.pointings_ecl[:, start:stop])
    np.testing.assert_array_equal(segment.hwp_angle_rad, recording.hwp_angle_rad[start:stop])
    shift_s = (segment.start_time - recording.start_time).to_value("s")
    assert shift_s == pytest.approx(start / recording.sampling_rate_hz, abs=1e-6)
    assert segment.times_s[0] == 0.0
    with pytest.raises(RecordingError, match=r"rec.h5: samples 5000:4000"):
        read_recording(path, samples=(5000, 4000))


@pytest.mark.slow
def test_a_recording_in_two_segments_gives_the_effect_of_the_whole(tmp_path):
    """A 2 h pair with g1 = -3e-3, diagnosed at once and in two 1 h segments: the same
    effect; the combined g1 within the errors of the whole's, with a similar sigma."""
    g1_true = -3e-3
    recording, _ = recorded(tmp_path, [("tes_nonlinearity", {"g1": g1_true})], 7002)
    whole = run(recording, figures=False)
    segmented = diagnose_segments(
        tmp_path / "rec.h5",
        sky_map(),
        A2_K,
        out_dir=tmp_path / "out",
        segment_hours=1.0,
        figures=False,
    )
    assert segmented.effect_names == whole.effect_names == ["tes_nonlinearity"], segmented[
        "unexplained"
    ]
    assert len(segmented["segments"]) == 2
    assert segmented.effect("tes_nonlinearity")["segments"] == [0, 1]
    for k in range(2):
        combined = segmented.parameter("tes_nonlinearity", "g1", k)
        at_once = whole.parameter("tes_nonlinearity", "g1", k)
        assert abs(combined["value"] - at_once["value"]) < 3 * at_once["sigma"]
        assert abs(combined["value"] - g1_true) < 4 * combined["sigma"]
        assert 0.7 < combined["sigma"] / at_once["sigma"] < 1.5
        assert not combined["varies_between_segments"]
    report = (tmp_path / "out" / "diagnosis.md").read_text()
    assert "## Segments" in report and "segments/1/diagnosis.md" in report
    assert (tmp_path / "out" / "segments" / "1" / "diagnosis.json").exists()


def test_segments_without_a_nonlinearity_combine_their_bounds_on_g1():
    """No segment finds a nonlinearity: each one's g1 fitted beside its effects
    (requirement_check.parameters) combines as the inverse-variance mean, and the bound is
    |g1| + 2 sigma of that mean."""
    from hwp_tes_systematics.diagnose.bound.requirement_check import bound_nonlinearity

    results = []
    for value, sigma in ((1.0e-4, 4e-4), (-3.0e-4, 3e-4)):
        result = segment_result(0.0, 1.0)
        result["effects"] = []
        parameters = {"g1[d0]": entry(value, sigma)}
        result["requirement_check"] = {"effect": None} | bound_nonlinearity(
            parameters, REQUIREMENT, -1.0
        )
        results.append(result)
    combined = combine_segments(results, [(0, 3600), (3600, 7200)], 1.0, REQUIREMENT)
    check = combined["requirement_check"]
    assert check["effect"] is None and not check["detected"] and check["delta_chi2"] == -2.0
    weights = np.array([4e-4, 3e-4]) ** -2.0
    mean = np.sum(weights * [1.0e-4, -3.0e-4]) / weights.sum()
    (detector,) = check["detectors"]
    assert detector["g1_per_k"] == pytest.approx(mean)
    assert detector["bound_per_k"] == pytest.approx(abs(mean) + 2 * weights.sum() ** -0.5)
    assert check["sentence"].startswith("No TES nonlinearity found")
    json.dumps(combined)


def _with_drift(result: dict, chosen: str, other: str, margin: float) -> dict:
    """``result`` with ``chosen`` selected at step 2 and ``other`` its candidate there,
    ``margin`` behind in Delta BIC (both detected on their own)."""
    drift = {**result["effects"][0], "name": chosen, "parameters": {}, "look_alikes": []}
    candidates = {
        chosen: {"delta_chi2": -1e6, "delta_bic": -1e6},
        other: {"delta_chi2": -1e6 + margin, "delta_bic": -1e6 + margin},
        "glitches": {"delta_chi2": 0.0, "delta_bic": 0.0},
    }
    step = {"step": 2, "added": chosen, "removed": None, "candidates": candidates, "note": ""}
    return {**result, "effects": [*result["effects"], drift], "steps": [step]}


def test_effects_that_take_each_others_place_in_different_segments_are_named_look_alikes():
    """A gain drift in segments 0 and 2, the HWP's slow modulation in 1 in its place, each
    the other's detected alternative where it was added: both entries name the other, with
    the summed preference (-30 - 5 + 3 = -32: toward gain_drift); glitches found in one
    segment only, never an alternative elsewhere, pair with nothing."""
    base = segment_result(-3.0e-3, 1e-4)
    results = [
        _with_drift(
            segment_result(-3.0e-3, 1e-4, glitch_time_s=10.0),
            "gain_drift",
            "hwpss_slow_modulation",
            30.0,
        ),
        _with_drift(base, "hwpss_slow_modulation", "gain_drift", 3.0),
        _with_drift(base, "gain_drift", "hwpss_slow_modulation", 5.0),
    ]
    combined = combine_segments(results, [(0, 10), (10, 20), (20, 30)], 1.0, REQUIREMENT)
    by_name = {e["name"]: e for e in combined["effects"]}
    assert by_name["gain_drift"]["look_alikes"] == ["hwpss_slow_modulation"]
    assert by_name["hwpss_slow_modulation"]["look_alikes"] == ["gain_drift"]
    (pair,) = by_name["gain_drift"]["look_alikes_across_segments"]
    assert pair["segments"] == [[0, 2], [1]]
    assert pair["preference_delta_bic"] == pytest.approx(-32.0)
    assert "lean to it" in by_name["gain_drift"]["evidence"]
    assert "lean to gain_drift" in by_name["hwpss_slow_modulation"]["evidence"]
    assert by_name["glitches"]["look_alikes"] == []
    assert by_name["tes_nonlinearity"]["look_alikes"] == []
    json.dumps(combined)
    # the same segments where the other was no alternative (below detection): no pair
    quiet = [_with_drift(base, "gain_drift", "hwpss_slow_modulation", 1e6 - 1.0), results[1]]
    combined = combine_segments(quiet, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    assert all(not e["look_alikes"] for e in combined["effects"])


def test_the_look_alike_verdict_reads_the_final_margins_where_every_segment_logged_one():
    """The steps' margins lean to gain_drift (-30 + 3 = -27), but under each segment's final
    noise the swaps say otherwise (gain_drift ahead by 2 in segment 0, the slow modulation
    ahead by 12 in segment 1): the pair carries both sums and the verdict reads the final
    one, one kind of margin throughout; without margins in a segment it keeps the steps'."""
    base = segment_result(-3.0e-3, 1e-4)

    def margins(result, selected, other, margin):
        return {**result, "swap_margins": {"effects": {selected: {other: margin}}}}

    drift, slow = "gain_drift", "hwpss_slow_modulation"
    results = [
        margins(_with_drift(base, drift, slow, 30.0), drift, slow, 2.0),
        margins(_with_drift(base, slow, drift, 3.0), slow, drift, 12.0),
    ]
    combined = combine_segments(results, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    by_name = {e["name"]: e for e in combined["effects"]}
    (pair,) = by_name[drift]["look_alikes_across_segments"]
    assert pair["preference_delta_bic"] == pytest.approx(-27.0)
    assert pair["preference_final_delta_bic"] == pytest.approx(-2.0 + 12.0)
    assert pair["final_delta_bic_per_segment"] == [{0: -2.0}, {1: -12.0}]
    assert f"lean to {slow}" in by_name[drift]["evidence"]
    assert "under its final noise" in by_name[drift]["evidence"]
    results[1] = {k: v for k, v in results[1].items() if k != "swap_margins"}
    combined = combine_segments(results, [(0, 10), (10, 20)], 1.0, REQUIREMENT)
    (pair,) = {e["name"]: e for e in combined["effects"]}[drift]["look_alikes_across_segments"]
    assert "preference_final_delta_bic" not in pair
