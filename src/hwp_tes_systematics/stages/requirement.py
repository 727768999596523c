"""Stage: delta r versus sigma_g1 over all seeds, the quadratic fit and the requirement.

delta r = |r_sys - r_nosys| per realization; its mean over seeds versus sigma_g1 is
fitted by delta r = k sigma^2 (and, as a check, by a free power law); the requirement
is the sigma_g1 where k sigma^2 reaches the budget. delta r is quadratic in sigma_g1
only while it is small next to the likelihood's width sigma_r (beyond, the 68% point
grows faster than the added power): k is fitted on the points with mean delta r below
QUADRATIC_REGIME x sigma_r when there are at least two, else on all points.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd

from ..figures.results import plot_likelihoods, plot_requirement
from ..io import atomic_path, write_csv
from ..requirement import fit_power_law, fit_quadratic, requirement_sigma, summarise
from ..systematics import NOSYS

log = logging.getLogger(__name__)

QUADRATIC_REGIME = 0.1  # fraction of sigma_r below which delta r ~ sigma^2 holds (measured)


def config_hash(config: dict) -> str:
    """sha256 of the configuration (sorted JSON): which settings produced a result."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def delta_r_table(likelihood_jsons: list[str]) -> pd.DataFrame:
    rows = []
    for path in likelihood_jsons:
        result = json.loads(Path(path).read_text())
        r_nosys = result["cases"][NOSYS]["r_fraction"]
        for case, values in result["cases"].items():
            if case == NOSYS:
                continue
            rows.append(
                {
                    "seed": result["seed"],
                    "case": case,
                    "sigma_g1": values["sigma_g1_per_k"],
                    "r_sys": values["r_fraction"],
                    "r_nosys": r_nosys,
                    "delta_r": abs(values["r_fraction"] - r_nosys),
                    "sigma_r_fisher_0": result["sigma_r_fisher_0"],
                }
            )
    return pd.DataFrame(rows).sort_values(["sigma_g1", "seed"], ignore_index=True)


def run(
    config: dict,
    likelihood_jsons: list[str],
    table_csv: str,
    requirement_json: str,
    fig_likelihoods: str,
    fig_requirement: str,
) -> None:
    table = delta_r_table(likelihood_jsons)
    write_csv(table, table_csv)
    summary = summarise(table)
    sigma = summary["sigma_g1"].to_numpy()
    mean = summary["mean_delta_r"].to_numpy()
    sigma_r = float(table["sigma_r_fisher_0"].mean())
    quadratic = mean < QUADRATIC_REGIME * sigma_r
    used = quadratic if quadratic.sum() >= 2 else np.ones_like(quadratic)
    k = fit_quadratic(sigma[used], mean[used])
    amplitude, exponent, exponent_sigma = fit_power_law(sigma, mean)
    budget = config["requirement"]["delta_r_budget"]
    requirement = requirement_sigma(k, budget)
    output = {
        "requirement_sigma_g1_per_k": requirement,
        "delta_r_budget": budget,
        "quadratic_fit": {
            "k_per_k2": k,
            "model": "mean delta r = k sigma_g1^2",
            "sigma_g1_used_per_k": sigma[used].tolist(),
        },
        "power_law_fit": {
            "amplitude": amplitude,
            "exponent": exponent,
            "exponent_sigma": exponent_sigma,
        },
        "per_sigma": [
            {
                "sigma_g1_per_k": float(row.sigma_g1),
                "mean_delta_r": float(row.mean_delta_r),
                "std_delta_r": float(row.std_delta_r),
                "n_seeds": int(row.n_seeds),
            }
            for row in summary.itertuples()
        ],
        "n_seeds": int(table["seed"].nunique()),
        "sigma_r_fisher": sigma_r,
        "config_sha256": config_hash(config),
    }
    with atomic_path(requirement_json) as temporary:
        temporary.write_text(json.dumps(output, indent=1))
    log.info(
        "requirement: sigma_g1 < %.3e 1/K (k = %.3e, free exponent %.2f, %d seeds)",
        requirement,
        k,
        exponent,
        output["n_seeds"],
    )
    first = json.loads(Path(min(likelihood_jsons)).read_text())
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
    )
