"""An effect is one class in one file: registered, the engine finds, fits and reports it.

The toy effect below (a 7 f_HWP line, a harmonic the catalog does not hold) is defined in
this file alone. Registered (``register``), it joins the catalog page, a simulated
recording injects it by its name, and the diagnosis selects it and fits its amplitude;
unregistered, the same recording leaves its line in ``unexplained``.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import pytest

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.catalog import effect_catalog_markdown
from hwp_tes_systematics.diagnose.effects import (
    CATALOG,
    Effect,
    harmonic_templates,
    register,
    unregister,
)
from hwp_tes_systematics.diagnose.simulate import injectable
from hwp_tes_systematics.diagnose.testbed import (
    A2_K,
    nominal_errors,
    recorded_with_errors,
    supplied_sky,
)


class SeventhHwpHarmonic(Effect):
    """A toy effect: c7 cos 7(chi - theta) + s7 sin 7(chi - theta), a 7 f_HWP line."""

    name = "toy_hwpss_harmonic_7"
    title = "a 7 f_HWP line (a toy effect of the tests)"
    parameters: ClassVar[dict[str, str]] = {"c7": "K", "s7": "K"}
    main_parameters = ("c7",)
    signature = "a line at 7 f_HWP"
    discrimination = "no other effect makes a 7 f_HWP line"

    def templates(self, ctx):
        return harmonic_templates(ctx, (7,))

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)


@pytest.fixture
def toy_effect():
    register(SeventhHwpHarmonic)
    yield CATALOG[SeventhHwpHarmonic.name]
    unregister(SeventhHwpHarmonic)


@pytest.mark.slow
def test_a_registered_effect_is_found_fitted_and_reported(tmp_path, toy_effect):
    assert "(effect-SeventhHwpHarmonic)=" in effect_catalog_markdown()
    assert injectable(toy_effect.name) is toy_effect
    truth = {"c7": 30e-6, "s7": -20e-6}  # K: 36 uK, 11 times the white noise per mode here
    errors = nominal_errors(np.random.default_rng(71))
    recording, _ = recorded_with_errors(tmp_path, [(toy_effect.name, truth)], 3171, errors, 1.0)

    found = diagnose(recording, supplied_sky(errors), A2_K, figures=False)
    assert found.effect_names == [toy_effect.name], (found.effect_names, found["unexplained"])
    for parameter, value in truth.items():
        for detector in found["recording"]["detectors"]:
            entry = found.parameter(toy_effect.name, parameter, detector)
            assert abs(entry["value"] - value) < 3 * entry["sigma"], (parameter, entry)
    lines = [u for u in found["unexplained"] if u["kind"] == "line"]
    assert not any("7 f_HWP" in u["identification"] for u in lines), lines

    unregister(SeventhHwpHarmonic)  # the same recording, the catalog without it
    assert toy_effect.name not in CATALOG
    assert "SeventhHwpHarmonic" not in effect_catalog_markdown()
    missed = diagnose(recording, supplied_sky(errors), A2_K, figures=False)
    assert toy_effect.name not in missed.effect_names
    f_hwp = np.median(np.diff(np.unwrap(recording.hwp_angle_rad))) * recording.sampling_rate_hz
    seventh = 7 * f_hwp / (2 * math.pi)
    lines = [u for u in missed["unexplained"] if u["kind"] == "line"]
    assert any(abs(u["freq_hz"] - seventh) < 1e-3 for u in lines), (seventh, lines)


def test_registering_a_name_twice_is_refused():
    class Again(SeventhHwpHarmonic):
        name = "tes_nonlinearity"

    with pytest.raises(ValueError, match="tes_nonlinearity.*registered already"):
        register(Again)
    assert type(CATALOG["tes_nonlinearity"]).__name__ == "TesNonlinearity"
