"""Step 5 of the diagnosis: the nonlinearity g1 against the requirement of a workflow run."""

from __future__ import annotations

from ..effects import CATALOG, family_of
from ..select.bank import FitProblem
from ..select.step import Selection
from .requirement_check import (
    NONLINEARITY_FAMILY,
    SECOND_SOLUTION_DELTA_CHI2,
    bound_nonlinearity,
    compare_nonlinearity,
)


def bound_g1(effects: list[dict], selection: Selection, requirement: dict) -> dict:
    """Step 5: the nonlinearity against the requirement of a workflow run: the fitted g1
    if the nonlinearity was selected, else what the recording says of g1 all the same
    (its fit beside the effects found; :mod:`.requirement_check`)."""
    nonlinearity = next((e for e in effects if family_of(e["name"]) == NONLINEARITY_FAMILY), None)
    if nonlinearity is not None:
        seconds = _second_solutions(selection.final, nonlinearity["name"])
        return {
            "effect": nonlinearity["name"],
            **compare_nonlinearity(nonlinearity, requirement, seconds),
        }
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
    return bound_nonlinearity(
        parameters, requirement, beside.chi2 - final.chi2, _second_solutions(beside, name)
    )


def _second_solutions(fit, name: str) -> list[dict | None] | None:
    """Per detector, the g1 of the fit's other self-consistent solutions
    (``fit.alternatives``, :func:`..select.backfit.fit_composed`) that the recording cannot
    rule out (chi^2 within SECOND_SOLUTION_DELTA_CHI2 of the fit's) and that are another
    solution (g1 more than the fit's sigma away from the fit's): the one farthest from
    zero, {g1_per_k, sigma_per_k, delta_chi2}, or None; None without alternatives."""
    if not fit.alternatives or name not in fit.effects:
        return None
    parameter = "g1"  # of every effect of the family
    values, sigmas = fit.effects[name].values[parameter], fit.effects[name].sigmas[parameter]
    seconds = []
    for k, chi2 in enumerate(fit.chi2_per_detector):
        solutions = [
            {
                "g1_per_k": float(other.effects[name].values[parameter][k]),
                "sigma_per_k": float(other.effects[name].sigmas[parameter][k]),
                "delta_chi2": float(other.chi2_per_detector[k] - chi2),
            }
            for other in fit.alternatives
        ]
        others = [
            s
            for s in solutions
            if s["delta_chi2"] < SECOND_SOLUTION_DELTA_CHI2
            and abs(s["g1_per_k"] - values[k]) > sigmas[k]
        ]
        seconds.append(
            max(others, key=lambda s: abs(s["g1_per_k"]) + 2 * s["sigma_per_k"]) if others else None
        )
    return seconds
