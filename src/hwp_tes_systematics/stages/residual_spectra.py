"""Stage: spectra of the CMB residual of one (seed, case), and the model's noise terms.

From the HILC residual a_lm (masked, common beam): the pseudo-C_ell / w2 (the f_sky
correction) of the total residual and of its foreground part; the noise part is their
difference in a_lm. The likelihood's N_ell and C_FGres are the means over seeds of the
no-systematics noise and foreground residuals (:func:`noise_model`).
"""

from __future__ import annotations

import logging

import h5py
import numpy as np
import pandas as pd

from .. import spectra
from ..io import write_csv

log = logging.getLogger(__name__)

SPECTRA = ("tt", "ee", "bb", "te", "eb", "tb")


def residual_spectra(hilc_h5) -> pd.DataFrame:
    """C_ell [K^2] of the residual, foreground residual and noise residual (EE, BB)."""
    with h5py.File(hilc_h5) as hilc:
        residual = hilc["residual_alm"][()]
        foreground = hilc["foreground_residual_alm"][()]
        lmax, w2, fsky_eff = (hilc.attrs[key] for key in ("lmax", "w2", "fsky_eff"))
    table = {"ell": np.arange(lmax + 1)}
    for label, alm in (
        ("residual", residual),
        ("foreground_residual", foreground),
        ("noise_residual", residual - foreground),
    ):
        cl = spectra.pseudo_spectra(alm, lmax, w2)
        for index in (1, 2):
            table[f"{SPECTRA[index]}_{label}_k2"] = cl[index]
    out = pd.DataFrame(table)
    out["fsky_eff"] = fsky_eff
    return out


def run(hilc_h5: str, out_csv: str) -> None:
    table = residual_spectra(hilc_h5)
    write_csv(table, out_csv)
    log.info("wrote %s", out_csv)


def noise_model(nosys_spectra_csvs: list[str]) -> pd.DataFrame:
    """N_ell and C_FGres [K^2]: means over seeds of the no-systematics BB residuals."""
    tables = [pd.read_csv(path) for path in nosys_spectra_csvs]
    out = pd.DataFrame({"ell": tables[0]["ell"]})
    out["n_ell_bb_k2"] = np.mean([t["bb_noise_residual_k2"] for t in tables], axis=0)
    out["c_fg_res_bb_k2"] = np.mean([t["bb_foreground_residual_k2"] for t in tables], axis=0)
    out["fsky_eff"] = float(np.mean([t["fsky_eff"].iloc[0] for t in tables]))
    out["n_seeds"] = len(tables)
    return out


def run_noise_model(nosys_spectra_csvs: list[str], out_csv: str) -> None:
    write_csv(noise_model(nosys_spectra_csvs), out_csv)
    log.info("wrote %s from %d seeds", out_csv, len(nosys_spectra_csvs))
