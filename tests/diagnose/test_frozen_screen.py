"""The screen of the candidates on a composed fit, added at a forward step or put in an
effect's place at a swap (select.frozen): it skips only candidates that cannot pass, and
the diagnosis is otherwise the same to the bit."""

from __future__ import annotations

import math

from hwp_tes_systematics.diagnose.select import frozen
from hwp_tes_systematics.diagnose.testbed import recorded, run

CANDIDATES = "/candidates/"


def differences(a, b, path=""):
    """The paths where two JSON-like trees differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}/{k}" for k in set(a) ^ set(b)]
        for key in set(a) & set(b):
            out += differences(a[key], b[key], f"{path}/{key}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in differences(x, y, f"{path}[{i}]")
        ]
    both_nan = isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
    return [] if a == b or both_nan else [path]


def test_the_screen_leaves_the_diagnosis_as_the_full_fits_give_it(tmp_path, monkeypatch):
    """A nonlinearity with a gain drift: the candidates screened at each step (the time
    constant among them, by its linearised template) and the swaps screened in the
    drift's place are the ones
    whose full composed fit does not pass either (its Delta BIC above the threshold, its
    gain in chi^2 not beyond the screen's by half the penalty); every number of the report
    but the screened candidates' entries is identical."""
    effects = [("gain_drift", {"g1": [0.03, 0.02]}), ("tes_nonlinearity", {"g1": -0.04})]
    recording, _ = recorded(tmp_path, effects, noise_seed=110, hours=1.0)
    swaps = []  # the swaps the screen left out (a set without one of the current effects)
    screen = frozen.frozen_screen

    def spy(problem, selected, current):
        result = screen(problem, selected, current)
        if result is not None and not set(current.selected) <= set(selected):
            swaps.append(selected)
        return result

    with monkeypatch.context() as patch:
        patch.setattr(frozen, "frozen_screen", spy)
        screened = run(recording).to_dict()
    with monkeypatch.context() as patch:
        patch.setattr(frozen, "frozen_screen", lambda *args: None)
        full = run(recording).to_dict()
    assert sorted(e["name"] for e in screened["effects"]) == ["gain_drift", "tes_nonlinearity"]
    changed = differences(screened, full)
    assert all(CANDIDATES in path for path in changed), [p for p in changed if CANDIDATES not in p]
    threshold = screened["delta_bic_threshold"]
    count = 0
    for step, reference in zip(screened["steps"], full["steps"], strict=True):
        for name, entry in step["candidates"].items():
            if not entry.get("screened"):
                assert entry == reference["candidates"][name]
                continue
            count += 1
            truth = reference["candidates"][name]
            assert entry["delta_bic"] > 0 and truth["delta_bic"] > threshold, (name, entry, truth)
            # the full fit gains no more than half the penalty beyond the screen's gain (it
            # may gain less: a composed fit can land on a worse self-consistent solution)
            penalty = entry["delta_bic"] - entry["delta_chi2"]
            assert truth["delta_chi2"] - entry["delta_chi2"] > -0.5 * penalty, (name, entry, truth)
    assert count >= 10, count
    # the swap step's trials of the drift's look-alikes in its place were screened too; the
    # final swap margins (full fits) are among the identical numbers above
    assert len(swaps) >= 5, swaps
    assert screened["swap_margins"]["effects"]["gain_drift"]
    # the time constant, a nonlinear effect, is screened by its linearised template
    tau = [step["candidates"].get("detector_time_constant", {}) for step in screened["steps"]]
    assert any(entry.get("screened") for entry in tau), tau


def test_a_screened_candidate_is_fitted_in_full_when_asked_again(tmp_path, monkeypatch):
    """The screen's result is not cached: fit() of the same set gives the composed fit,
    whose chi^2 the screen's is close to (well within the candidate's BIC penalty)."""
    from hwp_tes_systematics.diagnose import pipeline

    kept = []

    def select_effects(*args, **kwargs):
        kept.append(selection := select(*args, **kwargs))
        return selection

    select = pipeline.select_effects
    monkeypatch.setattr(pipeline, "select_effects", select_effects)
    recording, _ = recorded(tmp_path, [("tes_nonlinearity", {"g1": -0.04})], 112, hours=1.0)
    run(recording)
    problem = kept[0].problem
    current = problem.fit(("tes_nonlinearity",))
    assert current.composition is not None
    candidate = ("tes_nonlinearity", "hwpss_harmonic_3")
    trial = problem.trial(candidate, current)
    assert trial.screened and trial.model_f is None
    fitted = problem.fit(candidate)
    assert not fitted.screened and fitted.composition is not None
    penalty = (fitted.n_params - current.n_params) * problem.ln_n_eff
    assert abs(fitted.chi2 - trial.chi2) < 0.5 * penalty
    assert trial.n_params == fitted.n_params


def test_a_screened_candidate_is_said_to_be_in_what_was_tried():
    """The unexplained structure's text names the effects tried at the last step, a
    screened one's Delta BIC marked as the screen's."""
    from types import SimpleNamespace

    from hwp_tes_systematics.diagnose.explain.unexplained import _rejected, _tried_text

    last = SimpleNamespace(
        added=None,
        removed=None,
        chi2_before=100.0,
        candidates={
            "gain_drift": {"delta_chi2": -1.0, "delta_bic": 45.0},
            "pointing_drift": {"delta_chi2": -2.0, "delta_bic": 88.0, "screened": True},
        },
    )
    tried = _rejected([last])
    assert tried == {"gain_drift": (45.0, False), "pointing_drift": (88.0, True)}
    text = _tried_text(tried, {})
    assert text == "gain_drift (Delta BIC +45), pointing_drift (Delta BIC +88, screened)"
