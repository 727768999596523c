"""Stage: spectra of the CMB residual of one (seed, case), and the model's noise terms.

From the HILC residual a_lm (masked, common beam): the pseudo-C_ell / w2 (the f_sky
correction), with the common beam deconvolved, of the total residual and of its
foreground part; the noise part is their difference in a_lm. All with the same
normalisation (:func:`ilc_residuals.unit_beam_spectra`). The likelihood's N_ell and
C_FGres are the means over seeds of the no-systematics noise and foreground residuals
(:func:`noise_model`). The systematic alone (:meth:`ilc_residuals.SeedMaps.systematic_spectra`)
is computed by the component separation, which holds the maps.
"""

from __future__ import annotations

import logging

import h5py
import pandas as pd

from .. import sky
from ..analysis import noise_model
from ..analysis.ilc_residuals import residual_spectra_table
from ..analysis.systematics import NOSYS, sigma_of_case
from ..figures.results import plot_residual_spectra
from ..io import write_csv

log = logging.getLogger(__name__)


def residual_spectra(hilc_h5) -> pd.DataFrame:
    """C_ell [K^2] of the residual, foreground residual and noise residual (EE, BB)."""
    with h5py.File(hilc_h5) as hilc:
        residual = hilc["residual_alm"][()]
        foreground = hilc["foreground_residual_alm"][()]
        cmb = {
            name: hilc[name][()] if name in hilc else None
            for name in (
                "cmb_input_alm",
                "cmb_filter_loss_alm",
                "cmb_leakage_alm",
                "cmb_input_b_alm",
                "cmb_recovered_b_only_alm",
                "tensor_input_b_alm",
                "tensor_recovered_b_alm",
            )
        }
        attrs = dict(hilc.attrs)
    fractions = {key: attrs[key] for key in ("w2", "fsky_eff")}
    return residual_spectra_table(
        residual, foreground, int(attrs["lmax"]), fractions, attrs["common_fwhm_arcmin"], **cmb
    )


def run(hilc_h5: str, out_csv: str) -> None:
    table = residual_spectra(hilc_h5)
    write_csv(table, out_csv)
    log.info("wrote %s", out_csv)


def run_noise_model(nosys_spectra_csvs: list[str], out_csv: str) -> None:
    write_csv(noise_model.measure(nosys_spectra_csvs), out_csv)
    log.info("wrote %s from %d seeds", out_csv, len(nosys_spectra_csvs))


def run_figure(
    config: dict, spectra_csvs: dict, systematic_csvs: list[str], out_png: str, out_csv: str
) -> None:
    """The residual BB spectra figure and its table: means over seeds of each case's
    residual (``spectra_csvs``: {case: [csv per seed]}) and of the systematic alone per unit
    sigma_g1^2 (``systematic_csvs``), beside the lensing and tensor BB."""
    grid = config["requirement"]["sigma_g1_per_k"]
    means = {
        case: pd.concat([pd.read_csv(path) for path in paths]).groupby("ell").mean()
        for case, paths in spectra_csvs.items()
    }
    nosys = means[NOSYS]
    ell = nosys.index.to_numpy()
    systematic = pd.concat([pd.read_csv(path) for path in systematic_csvs]).groupby("ell").mean()
    table = pd.DataFrame({"ell": ell})
    for case, case_means in means.items():
        table[f"bb_residual_{case}_k2"] = case_means["bb_residual_k2"].to_numpy()
    table["bb_noise_residual_nosys_k2"] = nosys["bb_noise_residual_k2"].to_numpy()
    table["bb_foreground_residual_nosys_k2"] = nosys["bb_foreground_residual_k2"].to_numpy()
    table["bb_systematic_per_sigma2_k4"] = systematic["bb_unit_k4"].to_numpy()
    table["n_seeds"] = len(systematic_csvs)
    write_csv(table, out_csv)
    lmax = int(ell.max())
    plot_residual_spectra(
        ell,
        {sigma_of_case(case, grid): table[f"bb_residual_{case}_k2"] for case in means},
        table["bb_systematic_per_sigma2_k4"],
        table["bb_noise_residual_nosys_k2"],
        table["bb_foreground_residual_nosys_k2"],
        sky.lensing_bb(lmax),
        sky.tensor_bb_r1(lmax),
        config["requirement"]["delta_r_budget"],
        out_png,
    )
    log.info("wrote %s and %s (%d seeds)", out_png, out_csv, len(systematic_csvs))
