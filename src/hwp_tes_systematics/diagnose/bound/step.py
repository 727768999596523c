"""Step 5 of the diagnosis: the nonlinearity g1 against the requirement of a workflow run."""

from __future__ import annotations

from ..effects import CATALOG, family_of
from ..select.bank import FitProblem
from ..select.step import Selection
from .requirement_check import NONLINEARITY_FAMILY, bound_nonlinearity, compare_nonlinearity


def bound_g1(effects: list[dict], selection: Selection, requirement: dict) -> dict:
    """Step 5: the nonlinearity against the requirement of a workflow run: the fitted g1
    if the nonlinearity was selected, else what the recording says of g1 all the same
    (its fit beside the effects found; :mod:`.requirement_check`)."""
    nonlinearity = next((e for e in effects if family_of(e["name"]) == NONLINEARITY_FAMILY), None)
    if nonlinearity is not None:
        return {"effect": nonlinearity["name"], **compare_nonlinearity(nonlinearity, requirement)}
    bound = _nonlinearity_bound(selection.problem, selection.final, requirement)
    return {"effect": None, **bound}


def _nonlinearity_bound(problem: FitProblem, final, requirement: dict) -> dict:
    """No nonlinearity selected: g1 fitted beside the final selection (the selection's last
    step tried it, so the fit is cached) bounds it (:func:`.requirement_check.bound_nonlinearity`)."""
    name = NONLINEARITY_FAMILY
    beside = problem.fit((*final.selected, name))
    effect = CATALOG[name]
    parameters = effect.reported_parameters(
        beside.effects[name],
        problem.ctx.detector_names,
        problem.ctx.sampling_rate_hz,
        problem.units[name],
    )
    return bound_nonlinearity(parameters, requirement, beside.chi2 - final.chi2)
