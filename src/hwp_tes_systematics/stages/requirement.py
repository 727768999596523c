"""Stage: delta r versus sigma_g1 over all seeds by two estimators, and the requirement.

The paper's estimator: delta r = |r_sys - r_nosys| per realization (68 % points, HILC
weights recomputed per case). Its mean over seeds is fitted by k sigma^2 on the points
of the quadratic regime (mean delta r < 0.1 sigma_r; :func:`requirement.assess_quadratic_regime`),
with a free power law as the check; when fewer than two points are in the regime, the
grid is extended downwards by decades (sigma_min / 10, ...; up to
``requirement.max_extra_decades``), each new point computed from the maps (they are
linear in g1: no new simulation). ``valid`` says whether sigma^2 describes the points.

The systematic-only estimator: delta r = k_seed sigma^2, the Fisher bias of the
systematic's BB through the no-systematics weights (rule likelihood), exactly
quadratic; its requirement sqrt(budget / mean k), with the scatter over seeds, for the
configured A_2 and for A_2 scaled by each of ``requirement.a2_scale_factors``.

The systematic alone is also given in the paper's convention, the shift of the 68 %
point (:func:`systematic_only.fraction_point_estimator`): the ``headline`` of
requirement.json, with the Fisher peak shift beside it. Before any of it is a
requirement, the stage checks that the likelihood model describes the data it is given
(:mod:`consistency`: the model's sky transfer and r = 0 BB against the run's measured
transfer and no-systematics residuals, per multipole bin); a configuration that fails
says so (``consistency.consistent`` false, ``headline.consistent`` false, Fig. 8).
Where in ell the information on r and the bias come from is tabulated and drawn.

Whatever the model, ``budget_crossing`` gives the sigma_g1 at which the paper's mean
delta r reaches the budget, interpolated between grid points (and per seed): the answer
when sigma^2 does not describe the points (at one year the CMB x systematic cross term,
linear in sigma_g1, dominates |r_sys - r_nosys|).
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd

from ..analysis import consistency
from ..analysis.fixed_instruments import (
    COMMON_MITIGATED,
    common_offset_estimator,
    delta_r_curves,
    fixed_instruments_summary,
)
from ..analysis.ilc_residuals import systematic_bb
from ..analysis.noise_model import ANALYSES, model_from_noise_table, residual_bb
from ..analysis.requirement import (
    budget_crossing_over_seeds,
    delta_r_table,
    figure8_arguments,
    fit_power_law,
    paper_estimator,
    requirement_sigma,
    summarise,
)
from ..analysis.run_summary import answer_table, describe_run, one_year_comparison, run_settings
from ..analysis.systematic_only import (
    fraction_point_estimator,
    mitigation_summary,
    systematic_only_estimator,
    template_split,
)
from ..figures.results import (
    plot_a2_scaling,
    plot_ell_distribution,
    plot_fixed_instruments,
    plot_likelihoods,
    plot_requirement,
)
from ..io import atomic_path, write_csv

log = logging.getLogger(__name__)


def config_hash(config: dict) -> str:
    """sha256 of the configuration (sorted JSON): which settings produced a result."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def run(
    config: dict,
    likelihood_jsons: list[str],
    table_csv: str,
    requirement_json: str,
    fig_likelihoods: str,
    fig_requirement: str,
    fig_a2_scaling: str,
    fig_ell_distribution: str,
    noise_csv: str,
    nosys_spectra_csvs: list[str],
    systematic_csvs: list[str],
    extension: dict | None = None,
    instrument_csvs: list[str] | None = None,
    fig_fixed_instruments: str | None = None,
    template_fit_jsons: list[str] | None = None,
    answer_csv: str | None = None,
) -> None:
    """The stage, in its steps: the model checked against the data, the paper's estimator
    on the delta r grid, the systematic alone (the headline's convention), fixed
    instruments and a common offset, then requirement.json and the figures.
    ``extension``: {"map_paths": {seed: {channel: maps or a_lm file}}, "nosys_spectra":
    {seed: csv}, "mask": the a_lm files' analysis mask or None} to extend the paper
    estimator's grid (None: no extension). ``instrument_csvs``: the seeds' fixed-instrument
    spectra (:mod:`fixed_instruments`), drawn in ``fig_fixed_instruments``;
    ``template_fit_jsons``: the seeds' template fit reports (component_separation), for the
    requirement after the fit when the likelihoods carry it."""
    likelihoods = sorted(
        (json.loads(Path(path).read_text()) for path in likelihood_jsons), key=lambda r: r["seed"]
    )
    budget = config["requirement"]["delta_r_budget"]
    settings = config["likelihood"]
    analysis = settings["model"]
    noise = pd.read_csv(noise_csv)
    model = model_from_noise_table(noise, settings["lmin"], settings["lmax"], analysis, noise_csv)
    if extension is not None:
        extension = dict(extension)
        extension["model"] = model
    nosys_tables = [pd.read_csv(path) for path in nosys_spectra_csvs]
    nosys_residuals = np.array(  # (seeds, ell) the no-systematics residual BB of the analysis
        [
            residual_bb(table, analysis, settings["lmax"], path)
            for table, path in zip(nosys_tables, nosys_spectra_csvs, strict=True)
        ]
    )
    check, distribution = model_checks(
        config, model, noise, nosys_tables, nosys_residuals, systematic_csvs, fig_ell_distribution
    )
    table = delta_r_table(likelihoods)
    grid_summary = summarise(table)
    table, regime = paper_estimator(table, config, extension)
    write_csv(table, table_csv)
    summary = summarise(table)
    amplitude, exponent, exponent_sigma = fit_power_law(
        summary["sigma_g1"].to_numpy(), summary["mean_delta_r"].to_numpy()
    )
    crossing = budget_crossing_over_seeds(table, budget)
    systematic_only = systematic_alone(
        likelihoods, table, budget, regime["sigma_r_fisher"], template_fit_jsons
    )
    fixed = fixed_instruments(
        instrument_csvs,
        model,
        budget,
        analysis,
        systematic_only,
        fig_fixed_instruments,
        nosys_residuals.mean(axis=0) if len(nosys_residuals) else None,
    )
    common = common_offset(instrument_csvs, model, budget, systematic_only, analysis)
    systematic_tables = [pd.read_csv(path) for path in systematic_csvs]
    systematic_only["template_split"] = split = template_split(systematic_tables, model, budget)
    if split is not None:
        log.info(
            "the template's split, shares of k: %s; without noise x h: sigma_g1 < %.3e 1/K",
            ", ".join(f"{pair} {share:.2f}" for pair, share in split["fraction_of_k"].items()),
            split["requirement_without_noise_h_per_k"],
        )

    def per_sigma(rows):
        return [
            {
                "sigma_g1_per_k": float(row.sigma_g1),
                "mean_delta_r": float(row.mean_delta_r),
                "std_delta_r": float(row.std_delta_r),
                "n_seeds": int(row.n_seeds),
            }
            for row in rows.itertuples()
        ]

    output = {
        "headline": headline(analysis, check, systematic_only, crossing, model),
        "consistency": check,
        "ell_distribution": distribution,
        "requirement_sigma_g1_per_k": requirement_sigma(regime["k_per_k2"], budget),
        "valid": regime["valid"],
        "delta_r_budget": budget,
        "quadratic_fit": {
            "k_per_k2": regime["k_per_k2"],
            "model": "mean delta r = k sigma_g1^2",
            "sigma_g1_used_per_k": regime["sigma_g1_used_per_k"],
        },
        "power_law_fit": {
            "amplitude": amplitude,
            "exponent": exponent,
            "exponent_sigma": exponent_sigma,
        },
        "regime": regime,
        "budget_crossing": crossing,
        "per_sigma": per_sigma(grid_summary),
        "extended_per_sigma": per_sigma(
            summary[~summary["sigma_g1"].isin(grid_summary["sigma_g1"])]
        ),
        "systematic_only": systematic_only,
        "fixed_instruments": fixed,
        "common_offset": common,
        "settings": run_settings(config),
        "n_seeds": len(likelihoods),
        "sigma_r_fisher": regime["sigma_r_fisher"],
        "config_sha256": config_hash(config),
    }
    output["headline"]["run"] = describe_run(config)
    output["headline"]["one_year_answer"] = one_year_comparison(
        output["headline"], output["settings"]
    )
    with atomic_path(requirement_json) as temporary:
        temporary.write_text(json.dumps(output, indent=1))
    if answer_csv is not None:
        write_csv(answer_table(output), answer_csv)
    log_results(output)
    first = likelihoods[0]
    grid = np.array(first["r_grid"])
    curves = {case: np.array(v["likelihood"]) for case, v in first["cases"].items()}
    r68 = {case: v["r_fraction"] for case, v in first["cases"].items()}
    plot_likelihoods(grid, curves, r68, fig_likelihoods, fraction=first["fraction"])
    plot_requirement(path=fig_requirement, **figure8_arguments(output, table))
    plot_a2_scaling(systematic_only["by_a2_scale"], budget, fig_a2_scaling)


def model_checks(
    config, model, noise, nosys_tables, nosys_residuals, systematic_csvs, fig_ell_distribution
) -> tuple[dict, dict]:
    """(the model check on all seeds with its held-out and r read-back checks, the
    information and bias per bin): :func:`model_check`, then
    :func:`consistency.held_out_check` and :func:`consistency.held_out_r_recovery`."""
    check, distribution = model_check(
        config, model, noise, nosys_residuals, systematic_csvs, fig_ell_distribution
    )
    check["held_out"] = consistency.held_out_check(config, nosys_tables)
    if check["held_out"] is not None:
        log.info(
            "model check on held-out seeds: %s",
            "; ".join(
                f"{split['model_from_data']}: "
                + ("consistent" if split["consistent"] else f"fails in {split['failing_bins']}")
                for split in check["held_out"]["splits"]
            ),
        )
    check["r_recovery"] = consistency.held_out_r_recovery(config, nosys_tables)
    return check, distribution


def systematic_alone(likelihoods, table, budget, sigma_r, template_fit_jsons) -> dict:
    """The systematic's own power: :func:`systematic_only.systematic_only_estimator` (Fisher),
    its free exponent, the paper's 68 %-point convention and, when the likelihoods carry
    it, the requirement after the template fit."""
    systematic_only = systematic_only_estimator(likelihoods, budget, sigma_r)
    systematic_summary = summarise(
        table.dropna(subset=["delta_r_systematic_only"]).assign(
            delta_r=lambda t: t["delta_r_systematic_only"]
        )
    )
    _, systematic_only["free_exponent"], systematic_only["free_exponent_sigma"] = fit_power_law(
        systematic_summary["sigma_g1"], systematic_summary["mean_delta_r"]
    )
    systematic_only["fraction_point"] = fraction_point_estimator(likelihoods, budget)
    if template_fit_jsons and all("mitigated" in r["systematic_only"] for r in likelihoods):
        fits = [json.loads(Path(path).read_text()) for path in template_fit_jsons]
        systematic_only["mitigated"] = mitigated = mitigation_summary(likelihoods, budget, fits)
        log.info(
            "after the template fit (%s): sigma_g1 < %.3e 1/K (68 %% point), %.3e (Fisher); "
            "the fit's own cost on r %.2e +- %.2e",
            mitigated["basis"],
            mitigated["requirement_sigma_g1_per_k"],
            mitigated["fisher_peak_shift_requirement_sigma_g1_per_k"],
            mitigated["fit_cost_delta_r"],
            mitigated["fit_cost_delta_r_sem"],
        )
    return systematic_only


def common_offset(instrument_csvs, model, budget, systematic_only, analysis) -> dict | None:
    """:func:`fixed_instruments.common_offset_estimator` of the seeds' instrument spectra
    (None without them), logged; with the template fit, the same of what the fit leaves of
    the common offset (beside the random population after the fit) goes to
    ``systematic_only["mitigated"]["common_offset"]``."""
    tables = [pd.read_csv(path) for path in instrument_csvs or []]
    unfiltered = analysis == "paper_literal"
    common = common_offset_estimator(tables, model, budget, systematic_only["k_per_k2"], unfiltered)
    mitigated = systematic_only.get("mitigated")
    if common is not None and mitigated is not None:
        mitigated["common_offset"] = after = common_offset_estimator(
            tables, model, budget, mitigated["k_per_k2"], unfiltered, COMMON_MITIGATED
        )
        if after is not None:
            log.info(
                "a g1 common to every detector, after the template fit: |mu| < %.3e 1/K "
                "(Fisher, b = %.2e +- %.2e, k_mu / k_sigma = %.2f)",
                after["requirement_mu_per_k"],
                after["b_per_k"],
                after["b_error_per_k"],
                after["k_over_k_random"],
            )
    if common is not None:
        log.info(
            "a g1 common to every detector: |mu| < %.3e 1/K (Fisher, b = %.2e +- %.2e, k_mu / "
            "k_sigma = %.2f); at sigma = 0.5 sigma_req, |mu| < %.3e",
            common["requirement_mu_per_k"],
            common["b_per_k"],
            common["b_error_per_k"],
            common["k_over_k_random"],
            common["allowed_region"][1]["mu_max_per_k"],
        )
    return common


def headline(analysis: str, check: dict, systematic_only: dict, crossing: dict, model) -> dict:
    """requirement.json's headline: the systematic's own power in the paper's convention,
    with the checks' verdicts and the other readings beside it."""
    fraction_point = systematic_only["fraction_point"]
    failing = ", ".join(f"ell {first}-{last}" for first, last in check["failing_bins"])
    return {
        "definition": "the systematic's own power in the paper's convention: sigma_g1 where "
        "the mean over seeds of the 68 %-point shift reaches the budget; error: bootstrap "
        "over seeds of that mean; std_over_seeds: the scatter of the seeds' own values",
        "model": analysis,
        "model_description": ANALYSES[analysis],
        "consistent": check["consistent"],
        "consistent_held_out": None
        if check["held_out"] is None
        else check["held_out"]["consistent"],
        "r_recovered_consistent": None
        if check["r_recovery"] is None
        else check["r_recovery"].get(analysis, {}).get("consistent"),
        "requirement_sigma_g1_per_k": fraction_point["requirement_sigma_g1_per_k"],
        "error_per_k": fraction_point["requirement_error_per_k"],
        "std_over_seeds_per_k": fraction_point["requirement_std_over_seeds_per_k"],
        "fisher_peak_shift_requirement_sigma_g1_per_k": systematic_only[
            "requirement_sigma_g1_per_k"
        ],
        "fisher_peak_shift_error_per_k": systematic_only["requirement_error_per_k"],
        "fisher_peak_shift_std_over_seeds_per_k": systematic_only[
            "requirement_std_over_seeds_per_k"
        ],
        "paper_estimator_budget_crossing_per_k": crossing["sigma_g1_per_k"],
        "sigma_r_fisher": model.fisher_sigma_r(0.0),
        "note": headline_note(analysis, check, failing),
    }


def headline_note(analysis: str, check: dict, failing: str) -> str:
    """The headline's verdict in words: the model check's, then the r read-back's."""
    if not check["consistent"]:
        return f"NOT a requirement: the likelihood model does not describe the data in {failing}"
    read_back = (check["r_recovery"] or {}).get(analysis, {})
    if read_back.get("consistent") is False:
        return (
            "the model check passes, but r read back on the no-systematics maps of "
            f"held-out seeds is {read_back['r_mean']:.3g} +- {read_back['r_sem']:.2g} for "
            f"r = {read_back['r_input']:g} (consistency.r_recovery): the model does not "
            "describe the data at that precision"
        )
    return "consistent: the likelihood model describes the data (consistency)"


def log_results(output: dict) -> None:
    """The requirement by every estimator, in the log."""
    requirement, k = output["requirement_sigma_g1_per_k"], output["quadratic_fit"]["k_per_k2"]
    exponent = output["power_law_fit"]["exponent"]
    exponent_sigma = output["power_law_fit"]["exponent_sigma"]
    regime, crossing = output["regime"], output["budget_crossing"]
    systematic_only, headline = output["systematic_only"], output["headline"]
    analysis = headline["model"]
    log.info(
        "paper estimator: sigma_g1 < %.3e 1/K (k = %.3e, free exponent %.2f +- %.2f, %d seeds)",
        requirement,
        k,
        exponent,
        exponent_sigma,
        output["n_seeds"],
    )
    if not regime["valid"]:
        log.warning("paper estimator: the sigma^2 model does not hold (%s)", regime["reason"])
    if crossing["outside_grid"] is None:
        log.info(
            "paper estimator, model-free: mean delta r reaches the budget at sigma_g1 = %.3e "
            "1/K (+- %.2e over %d seeds)",
            crossing["sigma_g1_per_k"],
            crossing["std_over_seeds_per_k"],
            crossing["n_seeds_crossing"],
        )
    else:
        log.info("paper estimator, model-free budget crossing: %s", crossing["outside_grid"])
    log.info(
        "systematic-only estimator, Fisher peak shift: sigma_g1 < %.3e 1/K (+- %.2e over "
        "seeds; k = %.3e)",
        systematic_only["requirement_sigma_g1_per_k"],
        systematic_only["requirement_std_over_seeds_per_k"],
        systematic_only["k_per_k2"],
    )
    log.info(
        "headline (%s, 68 %% point shift): sigma_g1 < %.3e 1/K (+- %.2e over seeds), "
        "sigma_r = %.3e; %s",
        analysis,
        headline["requirement_sigma_g1_per_k"],
        headline["std_over_seeds_per_k"],
        headline["sigma_r_fisher"],
        headline["note"],
    )
    log.info(
        "this run: %s; beside the year: %s", headline["run"], headline["one_year_answer"]["note"]
    )


def model_check(
    config: dict,
    model,
    noise: pd.DataFrame,
    residuals: np.ndarray,
    systematic_csvs: list[str],
    fig_ell_distribution: str,
) -> tuple[dict, dict]:
    """(:func:`consistency.check_model` of the analysis, the information and the bias per
    bin) and their figure. ``noise``: the noise model table; ``residuals``: (seeds, ell)
    the no-systematics residual BB of the analysis. The bias is that of the mean over
    seeds of the systematic's BB at sigma_g1 = 1."""
    settings = config["likelihood"]
    lmax = settings["lmax"]
    check, model_transfer, data_transfer = consistency.compare_model_with_data(
        settings, noise, noise, residuals
    )
    c_sys = np.mean(
        [systematic_bb(pd.read_csv(path).iloc[: lmax + 1], 1.0) for path in systematic_csvs],
        axis=0,
    )
    information, bias, distribution = consistency.information_and_bias(model, c_sys)
    plot_ell_distribution(
        model.ell, information, bias, model_transfer, data_transfer, check, fig_ell_distribution
    )
    return check, distribution


def fixed_instruments(
    instrument_csvs, model, budget, analysis, systematic_only, figure, c_res_nosys
) -> dict | None:
    """:func:`fixed_instruments.fixed_instruments_summary` of the seeds' instrument
    spectra, drawn in ``figure`` beside the study's own k sigma^2."""
    tables = [pd.read_csv(path) for path in instrument_csvs or []]
    fixed = fixed_instruments_summary(tables, model, budget, analysis, c_res_nosys)
    if fixed is not None and figure is not None:
        sigma = np.logspace(-5, -1, 200)
        plot_fixed_instruments(
            sigma,
            delta_r_curves(fixed["instruments"], sigma),
            fixed["instruments"],
            systematic_only["k_per_k2"],
            budget,
            model.fisher_sigma_r(),
            figure,
        )
    return fixed
