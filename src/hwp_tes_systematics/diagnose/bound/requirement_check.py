"""A fitted nonlinearity against the workflow's requirement on sigma_g1, in one sentence.

The study's requirement (``requirement.json``, ``headline``) bounds sigma_g1, the spread of
the detectors' g1 left after calibration (Micheli et al. 2024: g1 drawn per detector from
N(0, sigma_g1)). A diagnosis that measures g1 with uncertainty sigma says two things
against it: whether this recording knows g1 well enough (sigma below the requirement:
correcting with the fitted g1 leaves an error within it) and how large g1 itself is
against it (the bias a detector with this g1 would bring if left uncorrected). When no
nonlinearity is found, g1 fitted beside the effects that were bounds it instead:
|g1| < |g1_fit| + 2 sigma per detector (:func:`bound_nonlinearity`). Without a
file given, the shipped one-year result is used
(``docs/one_year/recovered_power/requirement.json``, packaged as
``data/one_year_requirement.json``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from scipy import stats

from ...config import ONE_YEAR_REQUIREMENT_SOURCE, one_year_requirement_path

NONLINEARITY_FAMILY = "tes_nonlinearity"
# a second solution of the fit beside (select.backfit.fit_composed) within this Delta chi^2
# of the first (2 sigma for one parameter) is one the recording cannot rule out
SECOND_SOLUTION_DELTA_CHI2 = 4.0


class RequirementFileError(ValueError):
    """A requirement.json that cannot be read or lacks what the comparison needs."""


def load_requirement(path=None) -> dict:
    """{source, sigma_g1_per_k, error_per_k, delta_r_budget, definition, settings, consistent}
    from a workflow's ``requirement.json`` (``path``; None: the shipped one-year result)."""
    if path is None:
        source = one_year_requirement_path()
        label = f"the shipped one-year result ({ONE_YEAR_REQUIREMENT_SOURCE})"
    else:
        source, label = Path(path), str(path)
    try:
        data = json.loads(source.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise RequirementFileError(f"{label}: cannot be read as JSON ({error})") from error
    try:
        headline = data["headline"]
        sigma = float(headline["requirement_sigma_g1_per_k"])
    except (KeyError, TypeError, ValueError) as error:
        raise RequirementFileError(
            f"{label}: no headline.requirement_sigma_g1_per_k ({error!r}); expected the "
            "results/requirement.json a workflow run writes"
        ) from error
    if not sigma > 0:
        raise RequirementFileError(f"{label}: requirement_sigma_g1_per_k = {sigma}: expected > 0")
    return {
        "source": label,
        "sigma_g1_per_k": sigma,
        "error_per_k": headline.get("error_per_k"),
        "delta_r_budget": data.get("delta_r_budget"),
        "definition": headline.get("definition", ""),
        "consistent": headline.get("consistent"),
        "settings": data.get("settings", {}),
    }


def _per_detector_g1(parameters: dict):
    """The report's g1 entries of each detector (a shared fit's common one left out)."""
    return (
        entry
        for entry in parameters.values()
        if entry["parameter"] == "g1" and entry["detector"] != "common"
    )


def compare_nonlinearity(effect: dict, requirement: dict, second_solutions=None) -> dict:
    """The fitted g1 of each detector (a report entry of the tes_nonlinearity family)
    against the requirement: sigma / requirement (how well this recording knows g1),
    |g1| / requirement (what an uncorrected g1 would bring), and the sentence. With
    ``second_solutions`` (per detector {g1_per_k, sigma_per_k, delta_chi2} or None), one
    within SECOND_SOLUTION_DELTA_CHI2 widens what the recording knows of g1 to
    ``uncertainty_per_k`` = max(sigma, |g1 - g1_2| + sigma_2)."""
    limit = requirement["sigma_g1_per_k"]
    detectors = []
    for k, entry in enumerate(_per_detector_g1(effect["parameters"])):
        uncertainty = entry["sigma"]
        row = {
            "detector": entry["detector"],
            "g1_per_k": entry["value"],
            "sigma_per_k": uncertainty,
        }
        second = _second_solution(second_solutions, k)
        if second is not None:
            row["second_solution"] = second
            spread = abs(entry["value"] - second["g1_per_k"]) + second["sigma_per_k"]
            uncertainty = max(uncertainty, spread)
        row.update(
            uncertainty_per_k=uncertainty,
            sigma_over_requirement=uncertainty / limit,
            g1_over_requirement=abs(entry["value"]) / limit,
        )
        detectors.append(row)
    return {
        "detected": True,
        "requirement": requirement,
        "detectors": detectors,
        "sentence": _sentence(detectors, requirement) + _second_solutions_text(detectors),
    }


def _second_solution(second_solutions, k: int) -> dict | None:
    """Detector k's second solution if the recording cannot rule it out (within
    SECOND_SOLUTION_DELTA_CHI2 of the fit), else None."""
    second = second_solutions[k] if second_solutions else None
    if second is None or second["delta_chi2"] >= SECOND_SOLUTION_DELTA_CHI2:
        return None
    return second


def _second_solutions_text(detectors) -> str:
    """The sentence on second solutions the recording cannot rule out ('' if none)."""
    seconds = [d for d in detectors if "second_solution" in d]
    if not seconds:
        return ""
    listed = ", ".join(
        f"{d['second_solution']['g1_per_k']:.2g} +- {d['second_solution']['sigma_per_k']:.2g} "
        f"({d['detector']}, Delta chi^2 = {d['second_solution']['delta_chi2']:.2g})"
        for d in seconds
    )
    return (
        f" A second solution fits as well (within Delta chi^2 = {SECOND_SOLUTION_DELTA_CHI2:g}): "
        f"g1 = {listed} K^-1: the nonlinearity shares a line with an effect found and only "
        "their cross terms tell the two apart, so what is said of g1 covers both."
    )


def bound_nonlinearity(
    parameters: dict, requirement: dict, delta_chi2: float, second_solutions=None
) -> dict:
    """No nonlinearity found: the g1 fitted beside the effects found (``parameters``, the
    report's entries of that fit) bounds it, |g1| < |g1_fit| + 2 sigma per detector (97.7 %
    on the side of the fit, more on the other), against the requirement;
    ``delta_chi2`` = chi^2 with g1 - chi^2 without (what adding it gained, <= 0), and p the
    chance of gaining as much from noise alone (chi^2 with n_detectors degrees of freedom):
    a small p is a nonlinearity below the selection's BIC threshold, not its absence.
    ``second_solutions``: per detector, the fit's other self-consistent solution {g1_per_k,
    sigma_per_k, delta_chi2} (None: none); within SECOND_SOLUTION_DELTA_CHI2 the bound
    covers it too (each solution's sigma is its own minimum's curvature)."""
    limit = requirement["sigma_g1_per_k"]
    detectors = []
    for k, entry in enumerate(_per_detector_g1(parameters)):
        sigma = entry["sigma"]  # None: not measured (combined over segments without one)
        bound = abs(entry["value"]) + 2 * sigma if sigma is not None else float("inf")
        row = {"detector": entry["detector"], "g1_per_k": entry["value"], "sigma_per_k": sigma}
        second = _second_solution(second_solutions, k)
        if second is not None:
            row["second_solution"] = second
            bound = max(bound, abs(second["g1_per_k"]) + 2 * second["sigma_per_k"])
        row.update(bound_per_k=bound, bound_over_requirement=bound / limit)
        detectors.append(row)
    fitted = ", ".join(
        f"{d['g1_per_k']:.2g} +- {_or_unknown(d['sigma_per_k'])} ({d['detector']})"
        for d in detectors
    )
    ratios = [d["bound_over_requirement"] for d in detectors]
    bounds = ", ".join(format(d["bound_per_k"], ".2g") for d in detectors)
    verdict = (
        f"each detector's |g1| is below the requirement ({_span(ratios)} of it)"
        if max(ratios) < 1
        else f"this recording cannot show |g1| below the requirement (its bound is "
        f"{_span(ratios)} times it)"
    )
    # the chance that noise alone gains as much: -Delta chi^2 ~ chi^2(n_detectors)
    p_value = float(stats.chi2.sf(-delta_chi2, len(detectors))) if detectors else 1.0
    sentence = (
        f"No TES nonlinearity found: fitted beside the effects found, g1 = {fitted} K^-1 "
        f"(Delta chi^2 = {delta_chi2:.3g} for {len(detectors)} parameters, p = {p_value:.2g} "
        "from noise alone), so |g1| < "
        f"{bounds} K^-1 (|g1| + 2 sigma) "
        f"against the requirement sigma_g1 < {_bound_text(requirement)} K^-1 "
        f"({_context(requirement)}): {verdict}." + _second_solutions_text(detectors)
    )
    return {
        "detected": False,
        "requirement": requirement,
        "detectors": detectors,
        "parameters": parameters,  # the fit's entries, for segments to combine
        "delta_chi2": delta_chi2,
        "p_value": p_value,
        "sentence": sentence,
    }


def _or_unknown(sigma) -> str:
    return "unknown" if sigma is None else format(sigma, ".2g")


def _bound_text(requirement) -> str:
    error = requirement["error_per_k"]
    return f"{requirement['sigma_g1_per_k']:.2g}" + (f" +- {error:.1g}" if error else "")


def _context(requirement) -> str:
    settings = requirement["settings"]
    context = []
    if requirement["delta_r_budget"] is not None:
        context.append(f"delta r < {requirement['delta_r_budget']:g}")
    if "duration_days" in settings:
        context.append(f"{settings['duration_days']:g} days")
    if "nside" in settings:
        context.append(f"nside {settings['nside']}")
    return "; ".join(part for part in (", ".join(context), requirement["source"]) if part)


def significant(value: float, digits: int = 2) -> str:
    """``value`` to ``digits`` significant figures, trailing zeros kept: 4.98e-3 / 4.9e-3
    is "1.0", not "1" (what ``format(value, ".2g")`` gives); a ratio from 10^digits up to
    1e6 as a rounded integer (189 -> "190", not "1.9e+02")."""
    if not math.isfinite(value) or value == 0:
        return format(value, "g")
    text = format(value, f"#.{digits}g")
    if "e+" in text and abs(value) < 1e6:
        return str(int(float(text)))
    return text if "e" in text else text.rstrip(".")


def _span(values, digits: int = 2) -> str:
    """The range of ratios, each to ``digits`` significant figures ("1.0" or "0.98-1.2")."""
    low, high = significant(min(values), digits), significant(max(values), digits)
    return low if low == high else f"{low}-{high}"


def _sentence(detectors, requirement) -> str:
    fitted = ", ".join(
        f"{d['g1_per_k']:.3g} +- {d['sigma_per_k']:.2g} ({d['detector']})" for d in detectors
    )
    sigma_ratio = [d["sigma_over_requirement"] for d in detectors]
    known = (
        f"this recording knows g1 {_span([1 / r for r in sigma_ratio])} times better "
        "than required (correcting with it meets the requirement)"
        if max(sigma_ratio) < 1
        else f"this recording knows g1 only to {_span(sigma_ratio)} times the "
        "requirement (not enough to correct with it)"
    )
    uncorrected = _span([d["g1_over_requirement"] for d in detectors])
    return (
        f"Fitted g1 = {fitted} K^-1 against the requirement sigma_g1 < "
        f"{_bound_text(requirement)} K^-1 ({_context(requirement)}): {known}, and left uncorrected "
        f"|g1| is {uncorrected} times the requirement."
    )
