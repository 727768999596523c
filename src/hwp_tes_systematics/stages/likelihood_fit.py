"""Stage: r from the Hamimeche-Lewis likelihood for every case of one realization, and
the systematic-only bias.

C_obs = C_res + C_lens and C_mod(r) = r C_GW(r=1) + C_lens + C_FGres + N_ell (paper eq. 10),
with C_lens and C_GW from the PTEP spectra shipped with litebird_sim and N_ell, C_FGres
from the noise model; ``likelihood.model`` (:data:`noise_model.ANALYSES`) says what the
residual is taken against and whether C_lens and C_GW carry the sky's measured transfer.
All cases of a seed are fitted on one r grid, so the grid's discretisation cancels in
delta r = |r_sys - r_nosys| (the paper's estimator). The systematic alone (its BB
through the no-systematics weights) is given in both conventions: the shift of the
likelihood's peak, the Fisher bias delta r = k sigma^2 exactly (k per HWPSS scale
factor), and the shift of its 68 % point (the paper's delta r), found numerically
through the likelihood on a grid of sigma_g1 (:func:`likelihood.fraction_point_shift`).
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd

from ..analysis.ilc_residuals import systematic_bb
from ..analysis.likelihood import fisher_bias, fit_r_common_grid, fraction_point_shift
from ..analysis.noise_model import model_from_noise_csv, residual_bb
from ..analysis.systematics import NOSYS, sigma_of_case
from ..io import atomic_path

log = logging.getLogger(__name__)

CURVE_POINTS = 801  # points of L(r) kept for the figure
# sigma_g1 [1/K] at which the 68 %-point shift of the systematic's own power is computed:
# 4 per decade, 1e-5 to 1 (the requirement interpolates between them)
SHIFT_SIGMAS_PER_K = np.logspace(-5.0, 0.0, 21)
SHIFT_STOP_OVER_BUDGET = 1e3  # larger sigmas are not computed once the shift exceeds this x budget


def run(
    config: dict,
    seed: int,
    spectra_csvs: dict[str, str],
    noise_csv: str,
    systematic_csv: str,
    out_json: str,
):
    settings = config["likelihood"]
    lmax = settings["lmax"]
    analysis = settings["model"]
    model = model_from_noise_csv(noise_csv, settings["lmin"], lmax, analysis)
    cases = list(spectra_csvs)
    residuals = [
        residual_bb(pd.read_csv(spectra_csvs[case]), analysis, lmax, spectra_csvs[case])
        for case in cases
    ]
    results = fit_r_common_grid(residuals, model, fraction=settings["fraction"])
    systematic = pd.read_csv(systematic_csv).iloc[: lmax + 1]
    shift = fraction_point_shift(
        residuals[cases.index(NOSYS)],
        systematic_bb(systematic, 1.0),
        model,
        SHIFT_SIGMAS_PER_K,
        settings["fraction"],
        stop_above=SHIFT_STOP_OVER_BUDGET * config["requirement"]["delta_r_budget"],
    )
    k_per_scale = {
        float(scale): fisher_bias(systematic_bb(systematic, scale), model)
        for scale in config["requirement"]["a2_scale_factors"]
    }
    k_unit = fisher_bias(systematic_bb(systematic, 1.0), model)
    keep = np.unique(np.linspace(0, results[0].r_grid.size - 1, CURVE_POINTS).astype(int))
    output = {
        "seed": seed,
        "fraction": settings["fraction"],
        "lmin": settings["lmin"],
        "lmax": lmax,
        "f_sky_eff": model.f_sky,
        "model": analysis,
        "sigma_r_fisher_0": results[0].sigma_r_fisher_0,
        "r_grid": results[0].r_grid[keep].tolist(),
        "cases": {
            case: {
                "sigma_g1_per_k": sigma_of_case(case, config["requirement"]["sigma_g1_per_k"]),
                "r_fraction": result.r_fraction,
                "r_ml": result.r_ml,
                "likelihood": result.likelihood[keep].tolist(),
            }
            for case, result in zip(cases, results, strict=True)
        },
        "systematic_only": {
            "model": "delta r = k sigma_g1^2 (Fisher bias of the systematic's BB through the "
            "no-systematics HILC weights)",
            "k_per_k2": k_unit,
            "k_per_k2_by_a2_scale": [
                {"a2_scale": scale, "k_per_k2": k} for scale, k in k_per_scale.items()
            ],
            "fraction_point_shift": {
                "definition": "r_f(C_nosys + sigma^2 C_sys) - r_f(C_nosys), the shift of the "
                "likelihood's fraction point (the paper's delta r) by the systematic's own power",
                "sigma_g1_per_k": SHIFT_SIGMAS_PER_K.tolist(),
                "delta_r": shift.tolist(),
            },
        },
    }
    if "bb_mitigated_k4" in systematic:
        output["systematic_only"]["mitigated"] = mitigated_systematic(
            config, model, residuals[cases.index(NOSYS)], systematic
        )
    with atomic_path(out_json) as temporary:
        temporary.write_text(json.dumps(output, indent=1))
    for case in cases:
        log.info(
            "seed %d %s: r(%.0f%%) = %.4e",
            seed,
            case,
            100 * settings["fraction"],
            output["cases"][case]["r_fraction"],
        )
    log.info("seed %d: systematic-only delta r = %.4e sigma_g1^2", seed, k_unit)


def mitigated_systematic(config: dict, model, nosys_residual, systematic) -> dict:
    """The systematic-only estimators after the template fit (mitigation.template_fit):
    the fit leaves sigma^2 C_mit of the systematic (``bb_mitigated_k4``) on a residual
    that has lost the sky along the templates, C_res' = C(res - D) = C_res - 2 C(res, D) +
    C(D); the Fisher bias k_mit, the 68 %-point shift of C_res' + sigma^2 C_mit, and the
    fit's own cost r_68(C_res') - r_68(C_res) (on one grid)."""
    settings = config["likelihood"]
    mitigated_nosys = (
        nosys_residual
        - 2.0 * systematic["bb_fit_removed_x_residual_k2"].to_numpy()
        + systematic["bb_fit_removed_k2"].to_numpy()
    )
    c_mitigated = systematic["bb_mitigated_k4"].to_numpy()
    shift = fraction_point_shift(
        mitigated_nosys,
        c_mitigated,
        model,
        SHIFT_SIGMAS_PER_K,
        settings["fraction"],
        stop_above=SHIFT_STOP_OVER_BUDGET * config["requirement"]["delta_r_budget"],
    )
    before, after = fit_r_common_grid(
        [nosys_residual, mitigated_nosys], model, settings["fraction"]
    )
    return {
        "basis": config["mitigation"]["template_fit"],
        "k_per_k2": fisher_bias(c_mitigated, model),
        "fraction_point_shift": {
            "definition": "r_f(C_res' + sigma^2 C_mit) - r_f(C_res'), C_res' the residual "
            "without the systematic after the fit, C_mit what the fit leaves of it",
            "sigma_g1_per_k": SHIFT_SIGMAS_PER_K.tolist(),
            "delta_r": shift.tolist(),
        },
        "fit_cost_delta_r": after.r_fraction - before.r_fraction,
    }
