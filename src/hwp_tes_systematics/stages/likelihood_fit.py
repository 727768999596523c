"""Stage: r from the Hamimeche-Lewis likelihood for every case of one realization.

C_obs = C_res + C_lens and C_mod(r) = r C_GW(r=1) + C_lens + C_FGres + N_ell (paper eq. 8),
with C_lens and C_GW from the PTEP spectra shipped with litebird_sim and N_ell, C_FGres
from the noise model. All cases of a seed are fitted on one r grid, so the grid's
discretisation cancels in delta r = |r_sys - r_nosys|.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd

from ..io import atomic_path
from ..likelihood import BBModel, fit_r_common_grid
from ..systematics import sigma_of_case

log = logging.getLogger(__name__)

CURVE_POINTS = 801  # points of L(r) kept for the figure


def model_from_noise_csv(noise_csv: str, lmin: int, lmax: int) -> BBModel:
    noise = pd.read_csv(noise_csv)
    if lmax > noise["ell"].iloc[-1]:
        raise ValueError(
            f"likelihood.lmax = {lmax} exceeds the spectra's lmax "
            f"{noise['ell'].iloc[-1]} ({noise_csv})"
        )
    return BBModel.from_ptep(
        f_sky=float(noise["fsky_eff"].iloc[0]),
        lmin=lmin,
        lmax=lmax,
        n_ell=noise["n_ell_bb_k2"].to_numpy()[: lmax + 1],
        c_fg_res=noise["c_fg_res_bb_k2"].to_numpy()[: lmax + 1],
    )


def run(config: dict, seed: int, spectra_csvs: dict[str, str], noise_csv: str, out_json: str):
    settings = config["likelihood"]
    model = model_from_noise_csv(noise_csv, settings["lmin"], settings["lmax"])
    cases = list(spectra_csvs)
    residuals = [
        pd.read_csv(spectra_csvs[case])["bb_residual_k2"].to_numpy()[: settings["lmax"] + 1]
        for case in cases
    ]
    results = fit_r_common_grid(residuals, model, fraction=settings["fraction"])
    keep = np.unique(np.linspace(0, results[0].r_grid.size - 1, CURVE_POINTS).astype(int))
    output = {
        "seed": seed,
        "fraction": settings["fraction"],
        "lmin": settings["lmin"],
        "lmax": settings["lmax"],
        "f_sky_eff": model.f_sky,
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
