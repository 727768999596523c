"""Gaps change nothing but the precision (issue 29): the same recording with stretches of
NaN (or flagged samples) gives the same effects, with parameters within their errors, and a
clean recording with a gap raises no alarm. A 2 h M1-140 pair, g1 = -3e-3 (the diagnosis
absorbs the constant part of every effect with an offset fitted jointly when samples are
flagged: diagnose.fit.GAP_OFFSET)."""

import shutil

import h5py
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import read_recording
from hwp_tes_systematics.diagnose.testbed import recorded, run

pytestmark = pytest.mark.slow

G1 = -3e-3
# (start, length) [h] of the gap, and whether it is NaN in the TOD or a flags dataset
GAPS = [(0.5, 0.5, "nan"), (1.2, 0.1, "nan"), (0.0, 0.2, "nan"), (1.5, 0.3, "flags")]


def with_gap(clean_path, path, start_h, length_h, how):
    shutil.copy(clean_path, path)
    with h5py.File(path, "r+") as handle:
        rate = handle["tod"].attrs["sampling_rate_hz"]
        first, last = int(start_h * 3600 * rate), int((start_h + length_h) * 3600 * rate)
        if how == "nan":
            tod = handle["tod"][()]
            tod[:, first:last] = np.nan
            handle["tod"][...] = tod
        else:
            flags = np.zeros(handle["tod"].shape, dtype=bool)
            flags[:, first:last] = True
            handle.create_dataset("flags", data=flags)
    return read_recording(path)


@pytest.fixture(scope="module")
def nonlinear(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gaps")
    recording, _ = recorded(folder, [("tes_nonlinearity", {"g1": G1})], 5151, name="clean.h5")
    return folder, run(recording, figures=False)


@pytest.mark.parametrize(("start_h", "length_h", "how"), GAPS)
def test_a_gap_keeps_the_effect_and_its_value(nonlinear, start_h, length_h, how):
    folder, clean = nonlinear
    gapped = with_gap(folder / "clean.h5", folder / f"gap{start_h}.h5", start_h, length_h, how)
    assert gapped.flags.mean() == pytest.approx(length_h / 2.0, abs=1e-3)
    result = run(gapped, figures=False)
    assert result.effect_names == clean.effect_names == ["tes_nonlinearity"], (
        result.effect_names,
        result["unexplained"],
    )
    for k in range(2):
        with_gap_g1 = result.parameter("tes_nonlinearity", "g1", k)
        without = clean.parameter("tes_nonlinearity", "g1", k)
        # the gap's data are a subset: the two estimates differ by less than the gap's own error
        assert abs(with_gap_g1["value"] - without["value"]) < 3 * with_gap_g1["sigma"]
        # and the error grows as 1 / sqrt(v) (white noise at the nonlinearity's lines; the
        # gapped periodogram's modes counted as v independent ones each): it did not move
        ratio = with_gap_g1["sigma"] / without["sigma"]
        print(f"sigma ratio {ratio:.4f} expected {1 / np.sqrt(1 - length_h / 2.0):.4f}")
        assert ratio == pytest.approx(1 / np.sqrt(1 - length_h / 2.0), rel=0.03)


def test_a_clean_recording_with_a_gap_raises_no_alarm(tmp_path):
    recorded(tmp_path, [], 5252, name="clean.h5")
    gapped = with_gap(tmp_path / "clean.h5", tmp_path / "gap.h5", 0.7, 0.4, "nan")
    result = run(gapped, figures=False)
    assert not result.mismatch_found, (result.effect_names, result["unexplained"])


def test_a_gap_beside_a_strong_4f_line_changes_nothing(tmp_path):
    """H3-402 (A_2 = 3.8 K), g1 = -3e-3: a 4f line of g1 A_2^2 / 2 = 21 mK. Cut by a gap it
    leaks over the whole band; fitted as noise before the effects, it passed for a pole of
    27 ms and every later noise fit went wrong (four effects and 11 unexplained entries on
    a six-hour pair, docs/diagnosis/rates.md; on this three-hour one, a gain fluctuation
    and 7 entries). With and without the gap: the nonlinearity alone, g1 within the gap's
    error, nothing unexplained."""
    from hwp_tes_systematics.diagnose import diagnose
    from hwp_tes_systematics.diagnose.testbed import (
        nominal,
        nominal_errors,
        recorded_with_errors,
        supplied_sky,
    )

    a2 = nominal("H3-402")["a2_k"]
    errors = nominal_errors(np.random.default_rng(5353))
    recording, _ = recorded_with_errors(
        tmp_path,
        [("tes_nonlinearity", {"g1": G1})],
        5353,
        errors,
        hours=3.0,
        name="clean.h5",
        channel="H3-402",
    )
    sky = supplied_sky(errors)
    clean = diagnose(recording, sky, a2, figures=False)
    gapped = with_gap(tmp_path / "clean.h5", tmp_path / "gap.h5", 1.2, 0.3, "nan")
    result = diagnose(gapped, sky, a2, figures=False)
    for diagnosis in (clean, result):
        assert diagnosis.effect_names == ["tes_nonlinearity"], (
            diagnosis.effect_names,
            diagnosis["unexplained"],
        )
        assert not diagnosis["unexplained"]
    for k in range(2):
        with_gap_g1 = result.parameter("tes_nonlinearity", "g1", k)
        without = clean.parameter("tes_nonlinearity", "g1", k)
        assert abs(with_gap_g1["value"] - without["value"]) < 3 * with_gap_g1["sigma"]


@pytest.mark.parametrize(
    ("channel", "c4_k", "g1", "found"),
    [
        ("H3-402", 0.1, 0.0, ["hwpss_harmonics"]),
        ("H3-402", 0.02, G1, ["hwpss_harmonics", "tes_nonlinearity"]),
        # the nonlinearity's 4f line (0.1 mK) is inside the 5 mK one: it is not selected
        # (Delta BIC ~ +9), but its fit beside the harmonics finds it (~3 sigma each)
        ("M1-140", 5e-3, G1, ["hwpss_harmonics"]),
    ],
)
def test_an_hwpss_with_strong_higher_harmonics_beside_a_gap_changes_nothing(
    tmp_path, channel, c4_k, g1, found
):
    """A real HWPSS has lines at 4 f_HWP and 6 f_HWP too (the paper's eq. 1), which the
    diagnosis is not told: cut by a gap, an unmodelled line leaks over the whole band (as
    the nonlinearity's 4f line did, test above). Lines of 5-100 mK at 4f and a tenth of it
    at 6f, three hours, a 0.3 h gap: the same effects with and without it (the harmonics,
    with the nonlinearity beside them where injected), the lines' amplitudes within the
    gap's error, nothing unexplained. A nonlinearity not selected is still measured by its
    fit beside the effects found, reported against the requirement: its g1 within 3 sigma."""
    from hwp_tes_systematics.diagnose import diagnose
    from hwp_tes_systematics.diagnose.testbed import (
        nominal,
        nominal_errors,
        recorded_with_errors,
        supplied_sky,
    )

    seed = 5454 + int(1e3 * c4_k)
    harmonics = {"c4": c4_k, "s4": -0.5 * c4_k, "c6": 0.1 * c4_k}
    effects = [("hwpss_harmonics", harmonics)] + ([("tes_nonlinearity", {"g1": g1})] if g1 else [])
    errors = nominal_errors(np.random.default_rng(seed))
    recording, _ = recorded_with_errors(
        tmp_path, effects, seed, errors, hours=3.0, name="clean.h5", channel=channel
    )
    sky, a2 = supplied_sky(errors), nominal(channel)["a2_k"]
    clean = diagnose(recording, sky, a2, figures=False)
    gapped = with_gap(tmp_path / "clean.h5", tmp_path / "gap.h5", 1.2, 0.3, "nan")
    result = diagnose(gapped, sky, a2, figures=False)
    for diagnosis in (clean, result):
        assert diagnosis.effect_names == found, (diagnosis.effect_names, diagnosis["unexplained"])
        assert not diagnosis["unexplained"]
        check = diagnosis["requirement_check"]
        if "tes_nonlinearity" not in found:
            print(check["sentence"])
            assert check["effect"] is None
            for detector in check["detectors"]:
                assert abs(detector["g1_per_k"] - g1) < 3 * detector["sigma_per_k"]
                assert detector["bound_per_k"] > abs(g1)
    for name in ("c4", "s4", "c6"):
        for k in range(2):
            with_gap_value = result.parameter("hwpss_harmonics", name, k)
            without = clean.parameter("hwpss_harmonics", name, k)
            assert abs(with_gap_value["value"] - without["value"]) < 3 * with_gap_value["sigma"]
