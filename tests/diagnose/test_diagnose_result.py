"""The diagnosis's result object (diagnose.report.Diagnosis) on the example recording's
diagnosis.json (tests/data/example_diagnosis.json: the workflow's example, an M1-140 pair
with the electrothermal TES nonlinearity, reported as tes_nonlinearity_cubic)."""

import json
from pathlib import Path

import pytest

from hwp_tes_systematics.diagnose import Diagnosis

EXAMPLE = Path(__file__).parents[1] / "data" / "example_diagnosis.json"


@pytest.fixture
def result() -> Diagnosis:
    return Diagnosis.read(EXAMPLE)


def test_reads_as_the_json_it_holds(result):
    data = json.loads(EXAMPLE.read_text())
    assert dict(result) == data and len(result) == len(data)
    assert result["effects"] == data["effects"] and result.to_dict() == data
    assert json.loads(result.to_json()) == data


def test_json_round_trip(result, tmp_path):
    path = tmp_path / "diagnosis.json"
    path.write_text(result.to_json())
    assert Diagnosis.read(path) == result


def test_the_report_goes_to_the_exact_paths_and_survives_a_failing_figure(
    result, tmp_path, monkeypatch
):
    """write_outputs writes the JSON and the Markdown where it is told (the rule's declared
    outputs, ReportPaths); a figure that raises is named in the Markdown and loses
    neither file."""
    from hwp_tes_systematics.diagnose.report import ReportPaths, figures, write_outputs

    def failing(*args):
        raise ValueError("sigma: None")

    monkeypatch.setattr(figures, "diagnosis_figures", failing)
    paths = ReportPaths(tmp_path / "a" / "out.json", tmp_path / "b" / "report.md")
    write_outputs(result, paths, None, None, None, None, None, None, figures=True)
    assert Diagnosis.read(paths.json) == result
    text = paths.markdown.read_text()
    assert "The figures could not be drawn (ValueError: sigma: None)" in text
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["out.json", "report.md"]
    assert ReportPaths.of(tmp_path) == ReportPaths(
        tmp_path / "diagnosis.json", tmp_path / "diagnosis.md"
    )


def test_accessors(result):
    assert result.mismatch_found
    assert result.effect_names == ["tes_nonlinearity_cubic"]
    detectors = result["recording"]["detectors"]
    by_index = result.parameter("tes_nonlinearity_cubic", "g1", 1)
    assert by_index == result.parameter("tes_nonlinearity_cubic", "g1", detectors[1])
    assert by_index["detector"] == detectors[1] and by_index["unit"] == "1/K"
    # the electrothermal TES's expansion around the load gives g1 = -0.0434 K^-1
    assert -0.06 < by_index["value"] < -0.03
    gain = result.adjustment(0, "gain")
    assert gain == result["nominal_adjustments"][detectors[0]]["gain"]
    assert "tes_nonlinearity_cubic" in repr(result)


def test_missing_names_say_what_there_is(result):
    with pytest.raises(KeyError, match="found \\['tes_nonlinearity_cubic'\\]"):
        result.effect("gain_drift")
    with pytest.raises(KeyError, match="no value for detector"):
        result.parameter("tes_nonlinearity_cubic", "g1", "no_such_detector")


def test_markdown_says_what_was_found(result):
    text = result.to_markdown()
    assert text.startswith("# Diagnosis of a recording against its simulation")
    assert "**Mismatch found.**" in text and "tes_nonlinearity_cubic" in text


def test_a_found_nonlinearity_against_the_shipped_requirement(result):
    """The example's g1 (electrothermal TES, ~-0.04 K^-1, known to ~1e-4) against the shipped
    one-year requirement (sigma_g1 < 1.5e-3 K^-1): known far better than required, and
    about 27 times the requirement if left uncorrected."""
    from hwp_tes_systematics.diagnose.bound.requirement_check import (
        compare_nonlinearity,
        load_requirement,
    )

    requirement = load_requirement()
    shipped = json.loads(
        (Path(__file__).parents[2] / "docs/one_year/recovered_power/requirement.json").read_text()
    )
    assert requirement["sigma_g1_per_k"] == shipped["headline"]["requirement_sigma_g1_per_k"]
    check = compare_nonlinearity(result.effect("tes_nonlinearity_cubic"), requirement)
    assert len(check["detectors"]) == 2
    for detector in check["detectors"]:
        assert detector["sigma_over_requirement"] < 0.1
        assert 15 < detector["g1_over_requirement"] < 40
    sentence = check["sentence"]
    assert sentence.startswith("Fitted g1 = ") and sentence.endswith("times the requirement.")
    assert "better than required" in sentence and "365.25 days" in sentence
    assert sentence.rstrip(".").count(". ") == 0  # one sentence


def test_a_nonlinearity_not_found_is_bounded_against_the_requirement():
    """No nonlinearity selected: the g1 fitted beside the effects bounds |g1| by |g1| + 2
    sigma per detector; the verdict turns on the larger bound against sigma_g1."""
    from hwp_tes_systematics.diagnose.bound.requirement_check import (
        bound_nonlinearity,
        load_requirement,
    )

    requirement = load_requirement()
    limit = requirement["sigma_g1_per_k"]

    def parameters(*values_sigmas):
        return {
            f"g1[d{k}]": {
                "value": v,
                "sigma": s,
                "unit": "1/K",
                "detector": f"d{k}",
                "parameter": "g1",
            }
            for k, (v, s) in enumerate(values_sigmas)
        }

    tight = bound_nonlinearity(parameters((1e-4, 1e-4), (-2e-4, 2e-4)), requirement, -1.5)
    assert [d["bound_per_k"] for d in tight["detectors"]] == pytest.approx([3e-4, 6e-4])
    assert tight["detectors"][1]["bound_over_requirement"] == pytest.approx(6e-4 / limit)
    sentence = tight["sentence"]
    assert (
        sentence.startswith("No TES nonlinearity found") and "below the requirement (" in sentence
    )
    assert "Delta chi^2 = -1.5 for 2 parameters, p = 0.47" in sentence  # exp(-1.5 / 2)
    assert "365.25 days" in sentence
    assert sentence.rstrip(".").count(". ") == 0  # one sentence
    loose = bound_nonlinearity(parameters((1e-4, 1e-4), (-3e-3, limit)), requirement, -9.0)
    assert "cannot show |g1| below the requirement" in loose["sentence"]
    assert not loose["detected"] and tight["parameters"]["g1[d0]"]["value"] == 1e-4
    unmeasured = bound_nonlinearity(parameters((1e-4, None)), requirement, 0.0)
    assert unmeasured["detectors"][0]["bound_per_k"] == float("inf")
    assert "+- unknown" in unmeasured["sentence"] and "cannot show" in unmeasured["sentence"]


def test_a_requirement_file_without_a_headline_is_refused(tmp_path):
    from hwp_tes_systematics.diagnose.bound.requirement_check import (
        RequirementFileError,
        load_requirement,
    )

    (tmp_path / "other.json").write_text(json.dumps({"per_sigma": []}))
    with pytest.raises(RequirementFileError, match="other.json: no headline"):
        load_requirement(tmp_path / "other.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(RequirementFileError, match="broken.json: cannot be read as JSON"):
        load_requirement(tmp_path / "broken.json")


def test_physical_bounds_say_what_is_out():
    from hwp_tes_systematics.diagnose.effects import CATALOG
    from hwp_tes_systematics.diagnose.select import EffectFit

    coupling = CATALOG["hwpss_intensity_coupling"]
    inside = EffectFit("hwpss_intensity_coupling", values={"a2c": [0.02, -0.05], "a2s": [0.0, 0.0]})
    outside = EffectFit("hwpss_intensity_coupling", values={"a2c": [0.02, -0.35], "a2s": [0, 0]})
    assert coupling.unphysical(inside) is None
    assert coupling.unphysical(outside) == "|a2c| = 0.35 > 0.1"
    assert CATALOG["gain_drift"].unphysical(EffectFit("gain_drift", values={"g1": [1.0]}))
    assert CATALOG["hwpss_harmonic_4"].unphysical(EffectFit("x", values={"c4": [1.0]})) is None


def test_a_second_solution_within_four_in_chi2_widens_what_is_said_of_g1():
    """A fit with a second self-consistent solution (select.backfit.fit_composed): within
    Delta chi^2 < 4 the bound covers it and a found g1's uncertainty spans it; beyond, it
    is ignored."""
    from hwp_tes_systematics.diagnose.bound.requirement_check import (
        bound_nonlinearity,
        compare_nonlinearity,
        load_requirement,
    )

    requirement = load_requirement()
    parameters = {
        f"g1[d{k}]": {
            "value": v,
            "sigma": 1e-4,
            "unit": "1/K",
            "detector": f"d{k}",
            "parameter": "g1",
        }
        for k, v in enumerate((2e-4, -3e-4))
    }
    seconds = [
        {"g1_per_k": -5e-3, "sigma_per_k": 2e-3, "delta_chi2": 2.5},
        {"g1_per_k": 4e-3, "sigma_per_k": 1e-3, "delta_chi2": 9.0},
    ]
    bound = bound_nonlinearity(parameters, requirement, -3.0, seconds)
    assert [d["bound_per_k"] for d in bound["detectors"]] == pytest.approx([9e-3, 5e-4])
    assert "second_solution" in bound["detectors"][0]
    assert "second_solution" not in bound["detectors"][1]
    assert "A second solution fits as well" in bound["sentence"] and "(d0," in bound["sentence"]
    found = compare_nonlinearity({"parameters": parameters}, requirement, seconds)
    assert [d["uncertainty_per_k"] for d in found["detectors"]] == pytest.approx([7.2e-3, 1e-4])
    assert "A second solution fits as well" in found["sentence"]
    plain = compare_nonlinearity({"parameters": parameters}, requirement)
    assert "second solution" not in plain["sentence"]
