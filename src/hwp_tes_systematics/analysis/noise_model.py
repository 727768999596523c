"""The noise model: what the no-systematics seeds say the likelihood's model must hold.

The likelihood (:mod:`likelihood`, eq. 1) needs N_ell, C_FGres and the sky's transfer
as the filtered data carry them. :func:`measure` takes them from the seeds' residual
spectra (``noise_model.csv``): means over seeds of the residuals, the sky's end-to-end
transfer, the power the recovered map holds of the sky with its leakage into B, the
map's response to r on the seeds' tensor probes, and the HILC's chance correlations.
:func:`model_from_noise_table` builds the :class:`likelihood.BBModel` of each analysis
(:data:`ANALYSES`, ``likelihood.model``) from that table.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .. import sky
from .likelihood import BBModel

# ========================================================= the analyses of the residual
# likelihood.model: what the residual is taken against and what the model's sky is.
ANALYSES = {
    "paper_recipe": "residual against the CMB through the same filters, unfiltered "
    "C_lens and r C_GW in the model (the paper's eq. 10 as written)",
    "transfer_in_model": "residual against the CMB through the same filters, C_lens and "
    "r C_GW times the sky's end-to-end BB transfer T_ell measured in the run",
    "paper_literal": "residual against the unfiltered input CMB (the paper's words read "
    "literally: it keeps the CMB the filters removed), unfiltered model",
    "recovered_power": "residual against the CMB through the same filters; the model's CMB "
    "is the power the recovered map holds: P_ell C_lens plus the filters' and the mask's "
    "leakage into B measured in the run, and R_ell r C_GW (R_ell the map's response to r, "
    "measured on the seeds' tensor probes where they carry them, else the power of the "
    "lensing B modes the map holds, else T_ell^2), both times the HILC's chance "
    "correlation f_ell",
}
RESIDUAL_COLUMN = {
    "paper_recipe": "bb_residual_k2",
    "transfer_in_model": "bb_residual_k2",
    "recovered_power": "bb_residual_k2",
    "paper_literal": "bb_residual_unfiltered_cmb_k2",
}


def check_analysis(analysis: str) -> str:
    """``analysis`` if it is one of :data:`ANALYSES`, else ValueError naming them."""
    if analysis not in ANALYSES:
        raise ValueError(f"likelihood.model = {analysis!r}: expected one of {sorted(ANALYSES)}")
    return analysis


def residual_bb(table: pd.DataFrame, analysis: str, lmax: int, source: str = "") -> np.ndarray:
    """The BB residual [K^2] that ``analysis`` fits, ell = 0..lmax, from a residual
    spectra table (:func:`ilc_residuals.residual_spectra_table`)."""
    column = RESIDUAL_COLUMN[check_analysis(analysis)]
    if column not in table:
        raise ValueError(
            f"{source or 'residual spectra'}: no column {column!r} for likelihood.model = "
            f"{analysis!r} (made by an older component_separation: rerun it)"
        )
    return table[column].to_numpy()[: lmax + 1]


def sky_transfer_bb(noise: pd.DataFrame, lmax: int, source: str = "") -> np.ndarray:
    """The measured end-to-end BB transfer T_ell of the sky on ell = 0..lmax (noise model)."""
    if "sky_transfer_bb" not in noise:
        raise ValueError(
            f"{source or 'noise model'}: no sky_transfer_bb column (made by an older "
            "component_separation: rerun it and noise_model)"
        )
    return noise["sky_transfer_bb"].to_numpy()[: lmax + 1]


def _clipped_sky_transfer(noise: pd.DataFrame, lmax: int, source: str = "") -> np.ndarray:
    """The measured B-to-B transfer T_ell, 1 below ell = 2, clipped at 0 (a spectrum is
    not negative)."""
    transfer = sky_transfer_bb(noise, lmax, source).copy()
    transfer[:2] = 1.0
    return np.clip(transfer, 0.0, None)


def sky_b_power_transfer(noise: pd.DataFrame, lmax: int, source: str = "") -> np.ndarray:
    """The power of the sky's B modes the recovered map holds over their input power,
    ell = 0..lmax (1 below ell = 2, clipped at 0): the noise model's measured
    ``sky_b_power_transfer_bb`` where the run split the filters' leakage out (the
    map-domain path), else T_ell^2 (a filter that scales each mode)."""
    if "sky_b_power_transfer_bb" not in noise:
        return _clipped_sky_transfer(noise, lmax, source) ** 2
    power = noise["sky_b_power_transfer_bb"].to_numpy()[: lmax + 1].copy()
    power[:2] = 1.0
    return np.clip(power, 0.0, None)


def cmb_leakage_bb(noise: pd.DataFrame, lmax: int, source: str = "") -> np.ndarray:
    """The recovered CMB's BB that the sky's B modes do not explain [K^2], ell =
    0..lmax: the filters' and the mask's leakage of T and E into B, from the noise model
    (:func:`noise_model`)."""
    if "cmb_leakage_bb_k2" not in noise:
        raise ValueError(
            f"{source or 'noise model'}: no cmb_leakage_bb_k2 column for likelihood.model = "
            "recovered_power (made by an older component_separation: rerun it and noise_model)"
        )
    return noise["cmb_leakage_bb_k2"].to_numpy()[: lmax + 1]


def analysis_transfer(noise: pd.DataFrame, lmax: int, analysis: str, source: str = ""):
    """The T_ell (ell = 0..lmax) by which ``analysis`` multiplies C_lens: the measured
    sky transfer for ``transfer_in_model``; for ``recovered_power`` the recovered map's
    lensing power over C_lens, P_ell + leakage / C_lens with P_ell
    :func:`sky_b_power_transfer`; None (no transfer) for the others."""
    if check_analysis(analysis) not in ("transfer_in_model", "recovered_power"):
        return None
    transfer = _clipped_sky_transfer(noise, lmax, source)
    if analysis == "transfer_in_model":
        return transfer
    c_lens = sky.lensing_bb(lmax)
    leakage = np.divide(
        cmb_leakage_bb(noise, lmax, source), c_lens, out=np.zeros(lmax + 1), where=c_lens > 0
    )
    return (sky_b_power_transfer(noise, lmax, source) + leakage) * hilc_cmb_power_ratio(noise, lmax)


def tensor_response(noise: pd.DataFrame, lmax: int, source: str = "") -> np.ndarray:
    """The BB an r = 1 adds to the recovered map over C_GW^{r=1}, ell = 0..lmax (1 below
    ell = 2, clipped at 0): the noise model's ``tensor_response_bb``, measured on the
    seeds' tensor probes, where the run has them; else the power of the lensing B modes
    the map holds (:func:`sky_b_power_transfer`), which overstates it where the filters
    have removed the sky and the mask brings power in from other multipoles (the tensor's
    reionization bump falls where the lensing spectrum is flat)."""
    if "tensor_response_bb" not in noise:
        return sky_b_power_transfer(noise, lmax, source)
    response = noise["tensor_response_bb"].to_numpy()[: lmax + 1].copy()
    response[:2] = 1.0
    return np.clip(response, 0.0, None)


def hilc_cmb_power_ratio(noise: pd.DataFrame, lmax: int) -> np.ndarray:
    """The HILC map's CMB power with its chance correlation with the residual over the
    recovered CMB's own, f_ell = 1 + 2 C(CMB, residual) / C(CMB), ell = 0..lmax (noise
    model's ``hilc_cmb_power_ratio_bb``; ones where the run did not measure it). The
    weights, fitted on the data, anticorrelate the CMB with the residual (the ILC bias,
    Delabrouille et al. 2009): f < 1 where the CMB is a large part of the map. Taken to
    scale with the CMB's power (assumption), it multiplies the lensing and tensor terms.
    A power ratio cannot be negative: measured below zero (the chance correlation's noise,
    where the filters leave little of the sky) it is taken as 0."""
    if "hilc_cmb_power_ratio_bb" not in noise:
        return np.ones(lmax + 1)
    return np.clip(noise["hilc_cmb_power_ratio_bb"].to_numpy()[: lmax + 1], 0.0, None)


# the seeds' recovered CMB from the input's B modes alone, and that input (map-domain path)
B_ONLY_COLUMNS = ("bb_cmb_recovered_b_only_k2", "bb_cmb_input_b_k2")


def measure(nosys_spectra) -> pd.DataFrame:
    """N_ell and C_FGres [K^2]: means over seeds of the no-systematics BB residuals; and
    the sky's measured end-to-end BB transfer T_ell (filters, binning, mask, HILC):
    mean over seeds of C(recovered CMB, input CMB) over the mean of C(input CMB), with
    the standard error of the per-seed ratios (``sky_transfer_bb_sem``; 1 and 0 below
    ell = 2, where polarization has no power). With the recovered CMB's own BB, also the
    leakage ``cmb_leakage_bb_k2``, mean over seeds of C(recovered CMB) - T_ell^2 C(input
    CMB) (what the B-to-B transfer does not explain: E-to-B leakage; r-independent), and
    the power the map holds of a lensing-only sky over C_lens, T_ell^2 + leakage / C_lens
    (``sky_power_transfer_bb``, ``_sem`` over seeds; T_ell^2 for a filter that scales
    each mode). Where the seeds carry the filters' leakage apart (``bb_cmb_leakage_k2``,
    the map-domain path), the leakage is its mean and the power of the sky's B modes is
    measured, ``sky_b_power_transfer_bb`` = sum over seeds of C(recovered CMB less the
    leakage) over the sum of C(input CMB) (the likelihood's tensor response,
    :func:`sky_b_power_transfer`; else T_ell^2). Where the seeds also carry the input's B
    modes alone (``B_ONLY_COLUMNS``), the B power is measured on them, sum C(recovered
    from B) over sum C(input B), and the leakage is everything else the recovered CMB
    holds, C(recovered) - C(recovered from B): the filters' T and E leakage and the mask's
    E-to-B leakage of the pseudo-spectra, which no full-sky C_lens holds.
    The HILC's weights, fitted on the data, correlate the parts of its map by chance:
    ``noise_x_foreground_bb_k2`` is the mean residual BB less N_ell and C_FGres, and, where
    the seeds carry the map's own BB (``bb_recovered_k2``), ``cmb_x_residual_bb_k2`` the
    map's BB less the residual's and the recovered CMB's (twice their cross spectrum),
    ``hilc_cmb_power_ratio_bb`` = 1 + sum over seeds of it over the sum of C(recovered CMB)
    (:func:`hilc_cmb_power_ratio`), and ``sky_power_transfer_bb`` holds the cross term.
    ``nosys_spectra``: the seeds' residual spectra, as CSV paths or tables."""
    tables = [t if isinstance(t, pd.DataFrame) else pd.read_csv(t) for t in nosys_spectra]
    out = pd.DataFrame({"ell": tables[0]["ell"]})
    out["n_ell_bb_k2"] = np.mean([t["bb_noise_residual_k2"] for t in tables], axis=0)
    out["c_fg_res_bb_k2"] = np.mean([t["bb_foreground_residual_k2"] for t in tables], axis=0)
    # the residual's BB less its parts: twice the noise x foreground cross spectrum, which
    # the HILC's weights, fitted on the data, make negative (chance correlation)
    if all("bb_residual_k2" in t for t in tables):
        out["noise_x_foreground_bb_k2"] = (
            np.mean([t["bb_residual_k2"] for t in tables], axis=0)
            - out["n_ell_bb_k2"]
            - out["c_fg_res_bb_k2"]
        )
    if all("bb_cmb_input_k2" in t for t in tables):
        cross = np.array([t["bb_cmb_recovered_x_input_k2"] for t in tables])
        auto = np.array([t["bb_cmb_input_k2"] for t in tables])
        transfer, sem = measured_transfer(cross, auto)
        out["sky_transfer_bb"] = transfer
        out["sky_transfer_bb_sem"] = sem
        if all("bb_cmb_recovered_k2" in t for t in tables):
            recovered = np.array([t["bb_cmb_recovered_k2"] for t in tables])
            # per seed: C(the sky's B modes in the recovered map) / C(input)
            if all(c in t for t in tables for c in B_ONLY_COLUMNS):
                # the input's B modes alone: the leakage is all the T and E modes put in
                # B (the filters' and the mask's), the B power the rest
                b_only, b_input = (np.array([t[c] for t in tables]) for c in B_ONLY_COLUMNS)
                leakage = recovered - b_only
                b_power = np.divide(b_only, b_input, out=np.ones_like(auto), where=b_input > 0)
                out["sky_b_power_transfer_bb"] = measured_transfer(b_only, b_input)[0]
            elif all("bb_cmb_leakage_k2" in t for t in tables):
                leakage = np.array([t["bb_cmb_leakage_k2"] for t in tables])
                from_b = np.array([t["bb_cmb_recovered_b_k2"] for t in tables])
                b_power = np.divide(from_b, auto, out=np.ones_like(auto), where=auto > 0)
                out["sky_b_power_transfer_bb"] = measured_transfer(from_b, auto)[0]
            else:
                leakage = recovered - transfer**2 * auto  # per seed: r-independent
                b_power = np.broadcast_to(transfer**2, auto.shape)
            c_lens = sky.lensing_bb(int(out["ell"].iloc[-1]))
            in_map = leakage
            if all("bb_recovered_k2" in t and "bb_residual_k2" in t for t in tables):
                # the map's BB less the residual's and the recovered CMB's: twice their
                # cross spectrum, the HILC's chance correlation (ILC bias), taken to scale
                # with the CMB's power: a factor on the tensor response too
                map_bb = np.array([t["bb_recovered_k2"] for t in tables])
                residual = np.array([t["bb_residual_k2"] for t in tables])
                cross = map_bb - residual - recovered
                recovered_sum = recovered.sum(axis=0)
                ratio = np.ones(cross.shape[1])
                np.divide(
                    recovered_sum + cross.sum(axis=0),
                    recovered_sum,
                    out=ratio,
                    where=recovered_sum > 0,
                )
                ratio[:2] = 1.0
                out["cmb_x_residual_bb_k2"] = cross.mean(axis=0)
                out["hilc_cmb_power_ratio_bb"] = ratio
                in_map = leakage + cross
            power = b_power + np.divide(in_map, c_lens, out=np.zeros_like(in_map), where=c_lens > 0)
            power[:, :2] = 1.0
            out["cmb_leakage_bb_k2"] = leakage.mean(axis=0)
            out["sky_power_transfer_bb"] = power.mean(axis=0)
            out["sky_power_transfer_bb_sem"] = (
                power.std(axis=0, ddof=1) / np.sqrt(len(power)) if len(power) > 1 else 0.0
            )
    if all(c in t for t in tables for c in TENSOR_COLUMNS):
        out = out.join(tensor_response_columns(tables))
    out["fsky_eff"] = float(np.mean([t["fsky_eff"].iloc[0] for t in tables]))
    out["n_seeds"] = len(tables)
    return out


# the seeds' tensor probe (B modes alone at r = 1) recovered, and as put in (map-domain path)
TENSOR_COLUMNS = ("bb_tensor_recovered_b_k2", "bb_tensor_input_b_k2")


def tensor_response_columns(tables: list[pd.DataFrame]) -> pd.DataFrame:
    """The map's response to r from the seeds' tensor probes: ``tensor_response_bb`` =
    mean over seeds of C(recovered probe) / C_GW^{r=1}, the BB an r = 1 adds to the map
    per unit of the full-sky spectrum the model scales (filters, mask and weights, with
    the multipoles they mix; ``_sem`` over seeds), and ``tensor_input_over_theory_bb``,
    the same for the probe as put in (the mask's coupling alone: about 1 where C_GW is
    smooth). 1 and 0 below ell = 2."""
    recovered, put_in = (np.array([t[c] for t in tables]) for c in TENSOR_COLUMNS)
    c_gw = sky.tensor_bb_r1(recovered.shape[1] - 1)
    has_power = (np.arange(c_gw.size) >= 2) & (c_gw > 0)
    out = {}
    for name, spectra in (
        ("tensor_response_bb", recovered),
        ("tensor_input_over_theory_bb", put_in),
    ):
        ratio = np.divide(spectra, c_gw, out=np.ones_like(spectra), where=has_power)
        out[name] = ratio.mean(axis=0)
        if name == "tensor_response_bb":
            out[f"{name}_sem"] = (
                ratio.std(axis=0, ddof=1) / np.sqrt(len(ratio)) if len(ratio) > 1 else 0.0 * c_gw
            )
    return pd.DataFrame(out)


def measured_transfer(cross: np.ndarray, auto: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_ell = sum_seeds cross / sum_seeds auto, and the standard error of the mean of the
    per-seed ratios; (n_seeds, n_ell) in, T = 1 and error 0 where the input has no power."""
    total = auto.sum(axis=0)
    transfer = np.ones(total.size)
    np.divide(cross.sum(axis=0), total, out=transfer, where=total > 0)
    ratios = np.divide(cross, auto, out=np.ones_like(cross), where=auto > 0)
    sem = ratios.std(axis=0, ddof=1) / np.sqrt(len(ratios)) if len(ratios) > 1 else 0.0 * total
    return transfer, np.where(total > 0, sem, 0.0)


def model_from_noise_table(
    noise: pd.DataFrame, lmin: int, lmax: int, analysis: str = "paper_recipe", source: str = ""
) -> BBModel:
    """The likelihood's BB model of ``analysis`` (:data:`ANALYSES`) from the noise model
    table: C_FGres as measured, N_ell as measured plus the noise x foreground cross term
    (so that N + C_FGres is the residual's mean BB), C_lens times
    :func:`analysis_transfer` when it is not None, and C_GW times the same, or for
    ``recovered_power`` times the tensor response R_ell f_ell
    (:func:`tensor_response`, :func:`hilc_cmb_power_ratio`). Power cannot be negative: where
    the filters leave little of the sky, f_ell is measured on little CMB and can fall below
    zero (ell = 5 on half the seeds of a notch 4 f_HWP / 30 wide at nside 64); the tensor
    term is then none."""
    if lmax > noise["ell"].iloc[-1]:
        raise ValueError(
            f"likelihood.lmax = {lmax} exceeds the spectra's lmax "
            f"{noise['ell'].iloc[-1]} ({source or 'noise model'})"
        )
    n_ell = noise["n_ell_bb_k2"].to_numpy()[: lmax + 1]
    if "noise_x_foreground_bb_k2" in noise:
        n_ell = n_ell + noise["noise_x_foreground_bb_k2"].to_numpy()[: lmax + 1]
    model = BBModel.from_ptep(
        f_sky=float(noise["fsky_eff"].iloc[0]),
        lmin=lmin,
        lmax=lmax,
        n_ell=n_ell,
        c_fg_res=noise["c_fg_res_bb_k2"].to_numpy()[: lmax + 1],
    )
    transfer = analysis_transfer(noise, lmax, analysis, source)
    if transfer is None:
        return model
    tensor = None
    if analysis == "recovered_power":
        tensor = tensor_response(noise, lmax, source) * hilc_cmb_power_ratio(noise, lmax)
    return model.with_transfer(transfer, tensor)


def model_from_noise_csv(
    noise_csv: str, lmin: int, lmax: int, analysis: str = "paper_recipe"
) -> BBModel:
    """:func:`model_from_noise_table` of the noise model CSV ``noise_csv``."""
    return model_from_noise_table(pd.read_csv(noise_csv), lmin, lmax, analysis, noise_csv)
