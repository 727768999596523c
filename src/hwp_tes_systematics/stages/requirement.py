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

from ..figures.results import plot_a2_scaling, plot_likelihoods, plot_requirement
from ..io import atomic_path, write_csv
from ..likelihood import model_from_noise_csv
from ..requirement import (
    budget_crossing_over_seeds,
    delta_r_table,
    fit_power_law,
    paper_estimator,
    requirement_sigma,
    summarise,
    systematic_only_estimator,
)

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
    extension: dict | None = None,
) -> None:
    """``extension``: {"map_paths": {seed: {channel: maps}}, "nosys_spectra": {seed: csv},
    "noise_csv", "notch_csv"} to extend the paper estimator's grid (None: no extension)."""
    likelihoods = sorted(
        (json.loads(Path(path).read_text()) for path in likelihood_jsons), key=lambda r: r["seed"]
    )
    budget = config["requirement"]["delta_r_budget"]
    if extension is not None:
        settings = config["likelihood"]
        extension = dict(extension)
        extension["model"] = model_from_noise_csv(
            extension["noise_csv"], settings["lmin"], settings["lmax"], extension.get("notch_csv")
        )
    table = delta_r_table(likelihoods)
    grid_summary = summarise(table)
    table, regime = paper_estimator(table, config, extension)
    write_csv(table, table_csv)
    summary = summarise(table)
    sigma = summary["sigma_g1"].to_numpy()
    mean = summary["mean_delta_r"].to_numpy()
    sigma_r = regime["sigma_r_fisher"]
    k = regime["k_per_k2"]
    amplitude, exponent, exponent_sigma = fit_power_law(sigma, mean)
    requirement = requirement_sigma(k, budget)
    crossing = budget_crossing_over_seeds(table, budget)
    systematic_only = systematic_only_estimator(likelihoods, budget, sigma_r)
    systematic_summary = summarise(
        table.dropna(subset=["delta_r_systematic_only"]).assign(
            delta_r=lambda t: t["delta_r_systematic_only"]
        )
    )
    _, systematic_only["free_exponent"], systematic_only["free_exponent_sigma"] = fit_power_law(
        systematic_summary["sigma_g1"], systematic_summary["mean_delta_r"]
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
        "requirement_sigma_g1_per_k": requirement,
        "valid": regime["valid"],
        "delta_r_budget": budget,
        "quadratic_fit": {
            "k_per_k2": k,
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
        "settings": {
            "baseline_length_s": config["maps"]["baseline_length_s"],
            "g1_per": config["requirement"]["g1_per"],
            "notch_transfer_in_model": config["likelihood"]["notch_transfer_in_model"],
            "hwpss_a2_over_delta_p": config["optics"]["hwpss_a2_over_delta_p"],
            "duration_days": config["simulation"]["duration_days"],
            "nside": config["maps"]["nside"],
        },
        "n_seeds": len(likelihoods),
        "sigma_r_fisher": sigma_r,
        "config_sha256": config_hash(config),
    }
    with atomic_path(requirement_json) as temporary:
        temporary.write_text(json.dumps(output, indent=1))
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
        "systematic-only estimator: sigma_g1 < %.3e 1/K (+- %.2e over seeds; k = %.3e)",
        systematic_only["requirement_sigma_g1_per_k"],
        systematic_only["requirement_std_over_seeds_per_k"],
        systematic_only["k_per_k2"],
    )
    first = likelihoods[0]
    grid = np.array(first["r_grid"])
    curves = {case: np.array(v["likelihood"]) for case, v in first["cases"].items()}
    r68 = {case: v["r_fraction"] for case, v in first["cases"].items()}
    plot_likelihoods(grid, curves, r68, fig_likelihoods, fraction=first["fraction"])
    plot_requirement(
        sigma,
        mean,
        summary["std_delta_r"].to_numpy(),
        k,
        exponent,
        budget,
        requirement,
        fig_requirement,
        exponent_sigma=exponent_sigma,
        invalid_reason=None if regime["valid"] else regime["reason"],
        quadratic_threshold=regime["quadratic_threshold_delta_r"],
        crossing=crossing["sigma_g1_per_k"],
        systematic_only=(
            systematic_summary["sigma_g1"].to_numpy(),
            systematic_summary["mean_delta_r"].to_numpy(),
            systematic_summary["std_delta_r"].to_numpy(),
            systematic_only["k_per_k2"],
            systematic_only["requirement_sigma_g1_per_k"],
        ),
    )
    plot_a2_scaling(systematic_only["by_a2_scale"], budget, fig_a2_scaling)
