"""Stage: r from the Hamimeche-Lewis likelihood for every case of one realization, and
the systematic-only bias.

C_obs = C_res + C_lens and C_mod(r) = r C_GW(r=1) + C_lens + C_FGres + N_ell (paper eq. 8),
with C_lens and C_GW from the PTEP spectra shipped with litebird_sim and N_ell, C_FGres
from the noise model; with ``likelihood.notch_transfer_in_model`` C_lens and C_GW are
multiplied by the notch's BB transfer function (the spectra of a CMB that went through
the pipeline). All cases of a seed are fitted on one r grid, so the grid's
discretisation cancels in delta r = |r_sys - r_nosys| (the paper's estimator). The
systematic-only estimator is the Fisher bias of the systematic's spectrum through the
no-systematics weights (:func:`likelihood.fisher_bias`): delta r = k sigma^2 exactly,
given here as k per HWPSS scale factor.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd

from ..ilc_residuals import systematic_bb
from ..io import atomic_path
from ..likelihood import fisher_bias, fit_r_common_grid, model_from_noise_csv
from ..systematics import sigma_of_case

log = logging.getLogger(__name__)

CURVE_POINTS = 801  # points of L(r) kept for the figure


def run(
    config: dict,
    seed: int,
    spectra_csvs: dict[str, str],
    noise_csv: str,
    systematic_csv: str,
    out_json: str,
    notch_csv: str | None = None,
):
    settings = config["likelihood"]
    lmax = settings["lmax"]
    model = model_from_noise_csv(noise_csv, settings["lmin"], lmax, notch_csv)
    cases = list(spectra_csvs)
    residuals = [
        pd.read_csv(spectra_csvs[case])["bb_residual_k2"].to_numpy()[: lmax + 1] for case in cases
    ]
    results = fit_r_common_grid(residuals, model, fraction=settings["fraction"])
    systematic = pd.read_csv(systematic_csv).iloc[: lmax + 1]
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
        "notch_transfer_in_model": notch_csv is not None,
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
        },
    }
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
