"""The diagnosis's result object (diagnose.report.Diagnosis) on the example recording's
diagnosis.json (tests/data/example_diagnosis.json: the workflow's example, an M1-140 pair
with the electrothermal TES nonlinearity, reported as tes_nonlinearity_cubic)."""

import json
from pathlib import Path

import pytest

from hwp_tes_systematics.diagnose import Diagnosis

EXAMPLE = Path(__file__).parent / "data" / "example_diagnosis.json"


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
