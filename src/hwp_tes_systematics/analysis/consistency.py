"""Does the likelihood's model describe the data it is given? Checked per multipole bin.

The model of eq. (10) (:class:`likelihood.BBModel`) expects, at r = 0,

    C_mod(ell) = T_mod(ell) C_lens(ell) + N(ell) + C_FGres(ell)

with T_mod = 1 (the paper's recipe) or the measured transfer (``transfer_in_model``),
and responds to r through T_mod C_GW. What the filtered no-systematics data contain
at r = 0, measured in the run:

    C_data(ell) = T_data(ell) C_lens(ell) + <C_res^nosys(ell)>_seeds

with T_data the sky's end-to-end BB transfer (filters, binning, mask and HILC; noise
model's ``sky_transfer_bb``, the cross spectrum of the recovered and the input CMB over
the input's) and C_res the residual the analysis fits (against the filtered or, for
``paper_literal``, the unfiltered input CMB). Per bin b (lensing-weighted for the
transfers, (2 ell + 1)-weighted for the spectra) two comparisons:

* the sky: |T_mod,b - T_data,b| against 3 x the standard error of T_data,b over seeds;
  a model with tensor power where the filters left none claims information on r that
  the data cannot hold (sigma_r too small);
* the power: |C_data,b - C_mod,b| against 3 x the standard error of C_data,b over seeds
  (the residual's seed scatter; the transfer's error propagated).

A bin fails when a difference exceeds both its 3-sigma seed scatter and
``RELATIVE_TOLERANCE`` of the model's value (so that a real but immaterial difference,
1 % measured to 0.1 %, is not flagged), and for the sky at least ``SKY_TRANSFER_FLOOR``:
where the filters leave no sky, two transfers of 0.003 and -0.002 are one answer (a bin's
tensor information goes as T^2: a transfer of 0.01 holds 1e-4 of it), however precisely
their difference is measured (the nside-512 one-year run flagged ell 2-4 for a model
transfer of 3e-6 against -1.7e-3 +- 0.5e-3). The model is consistent when no bin of
lmin..lmax fails.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from .likelihood import (
    BBModel,
    fisher_bias_per_ell,
    fisher_information_per_ell,
    linear_r_estimate,
)
from .noise_model import (
    ANALYSES,
    analysis_transfer,
    measure,
    model_from_noise_table,
    residual_bb,
)

log = logging.getLogger(__name__)

MIN_SEEDS_FOR_VERDICT = 4  # below this, a standard error over seeds is not one

BIN_EDGES = (2, 5, 11, 21, 41, 81)  # first multipoles of the reported bins; the last runs to lmax
N_SIGMA = 3.0  # a difference beyond this many standard errors of the seed mean ...
RELATIVE_TOLERANCE = 0.1  # ... and beyond this fraction of the model's value fails; assumption
SKY_TRANSFER_FLOOR = 0.01  # ... and, for a transfer, beyond 1 % of full transmission; assumption


def bins(lmin: int, lmax: int) -> list[tuple[int, int]]:
    """Inclusive multipole bins [first, last] of BIN_EDGES clipped to lmin..lmax."""
    edges = sorted({max(lmin, edge) for edge in BIN_EDGES if edge <= lmax} | {lmin})
    return [
        (first, (edges[i + 1] - 1) if i + 1 < len(edges) else lmax) for i, first in enumerate(edges)
    ]


def _differs(difference: float, error: float, reference: float, floor: float = 0.0) -> bool:
    """|difference| beyond N_SIGMA x error and beyond max(RELATIVE_TOLERANCE x |reference|,
    floor)."""
    tolerance = max(RELATIVE_TOLERANCE * abs(reference), floor)
    return bool(abs(difference) > N_SIGMA * error and abs(difference) > tolerance)


def _weighted_sem(weight: np.ndarray, sem: np.ndarray) -> float:
    """Standard error of the weight-averaged bin from independent per-ell errors."""
    return float(np.sqrt(np.sum((weight * sem) ** 2)) / weight.sum())


def _bin_mean_sem(per_seed: np.ndarray, modes: np.ndarray) -> tuple[float, float]:
    """Mean over seeds of the (2 ell + 1)-weighted bin average, and its standard error."""
    binned = per_seed @ modes / modes.sum()
    sem = float(binned.std(ddof=1) / np.sqrt(binned.size)) if binned.size > 1 else 0.0
    return float(binned.mean()), sem


def check_model(
    base_model: BBModel,
    model_transfer,
    data_transfer,
    data_transfer_sem,
    residual_per_seed,
    model_noise_per_seed=None,
    model_transfer_sem=None,
) -> dict:
    """The per-bin comparison of the module docstring.

    ``base_model``: the model without any transfer (its C_lens, N, C_FGres, f_sky and
    ell range); ``model_transfer``: the T_mod(ell) the analysis multiplies C_lens and C_GW
    by (ones for the paper's recipe); ``data_transfer``, ``data_transfer_sem``: the
    measured T_data(ell) and its standard error, all on ``base_model.ell``;
    ``residual_per_seed``: (n_seeds, n_ell) the no-systematics residual BB [K^2] that
    the analysis fits, one row per seed. ``model_noise_per_seed`` ((n, n_ell), N + C_FGres
    of each seed the model was measured on) and ``model_transfer_sem`` (per ell): when
    the model comes from other seeds than the data (:func:`held_out_check`),
    its own standard errors, added in quadrature to the data's. Returns {"consistent", "failing_bins",
    "bins": [{"ell": [first, last], "model_transfer", "data_transfer",
    "data_transfer_sem", "model_bb_k2", "data_bb_k2", "data_bb_sem_k2",
    "data_over_model", "sky_consistent", "power_consistent"}], "criterion"}.
    """
    model = base_model
    residual = np.atleast_2d(np.asarray(residual_per_seed, dtype=float))
    n_seeds = residual.shape[0]
    if residual.shape[1] != model.ell.size:
        raise ValueError(
            f"residual_per_seed: {residual.shape[1]} multipoles, expected {model.ell.size}"
        )
    model_transfer = np.asarray(model_transfer, dtype=float)
    data_transfer = np.asarray(data_transfer, dtype=float)
    data_transfer_sem = np.asarray(data_transfer_sem, dtype=float)
    c_lens = model.c_lens
    noise = model.n_ell + model.c_fg_res
    model_noise = None if model_noise_per_seed is None else np.atleast_2d(model_noise_per_seed)
    model_transfer_sem = (
        np.zeros_like(model_transfer)
        if model_transfer_sem is None
        else np.asarray(model_transfer_sem, dtype=float)
    )
    rows = []
    for first, last in bins(model.lmin, model.lmax):
        where = (model.ell >= first) & (model.ell <= last)
        modes = 2 * model.ell[where] + 1.0
        lens_weight = modes * c_lens[where]
        t_model = float(np.sum(lens_weight * model_transfer[where]) / lens_weight.sum())
        t_data = float(np.sum(lens_weight * data_transfer[where]) / lens_weight.sum())
        t_sem = _weighted_sem(lens_weight, data_transfer_sem[where])
        t_model_sem = _weighted_sem(lens_weight, model_transfer_sem[where])
        lens_b = float(lens_weight.sum() / modes.sum())
        model_bb = t_model * lens_b + float(np.sum(modes * noise[where]) / modes.sum())
        residual_mean, residual_sem = _bin_mean_sem(residual[:, where], modes)
        data_bb = t_data * lens_b + residual_mean
        data_sem = float(np.hypot(residual_sem, t_sem * lens_b))
        model_sem = t_model_sem * lens_b
        if model_noise is not None:
            model_sem = float(np.hypot(model_sem, _bin_mean_sem(model_noise[:, where], modes)[1]))
        sky_ok = not _differs(
            t_model - t_data,
            float(np.hypot(t_sem, t_model_sem)),
            max(abs(t_model), abs(t_data)),
            SKY_TRANSFER_FLOOR,
        )
        power_ok = not _differs(data_bb - model_bb, float(np.hypot(data_sem, model_sem)), model_bb)
        rows.append(
            {
                "ell": [int(first), int(last)],
                "model_transfer": t_model,
                "data_transfer": t_data,
                "data_transfer_sem": t_sem,
                "model_bb_k2": model_bb,
                "data_bb_k2": data_bb,
                "data_bb_sem_k2": data_sem,
                "model_bb_sem_k2": model_sem,
                "data_over_model": data_bb / model_bb if model_bb > 0 else float("nan"),
                "sky_consistent": sky_ok,
                "power_consistent": power_ok,
            }
        )
    failing = [
        row["ell"] for row in rows if not (row["sky_consistent"] and row["power_consistent"])
    ]
    return {
        "consistent": not failing,
        "failing_bins": failing,
        "bins": rows,
        "n_seeds": int(n_seeds),
        "criterion": f"a bin fails when the model's sky transfer or its r = 0 BB differs from "
        f"the data's by more than {N_SIGMA:g} standard errors of the seed mean and more "
        f"than {RELATIVE_TOLERANCE:.0%} (a transfer: and more than {SKY_TRANSFER_FLOOR:g} "
        f"absolute) (module consistency)",
    }


def check_r_recovery(model: BBModel, recovered_per_seed, r_input: float) -> dict:
    """Does the model's response to r describe the map the analysis recovers?

    The paper's residual subtracts the input CMB, so an injected r never reaches its
    C_obs; this check reads r on the HILC's CMB map itself (``recovered_per_seed``:
    (n_seeds, n_ell) its BB [K^2], CMB + noise + foreground residual, one row per seed)
    with :func:`likelihood.linear_r_estimate` at r_f = ``r_input``, per seed. The model
    is right when the mean over seeds equals ``r_input``: consistent when they differ by
    less than N_SIGMA standard errors (no verdict, None, below MIN_SEEDS_FOR_VERDICT
    seeds). A model whose transfer (C_lens and C_GW) is not the sky's fails it: at
    r_input = 0 through the lensing power, at r_input > 0 through the tensor's too.
    Per bin, the recovered BB's mean over seeds against C_mod(r_input) locates a failure.
    """
    recovered = np.atleast_2d(np.asarray(recovered_per_seed, dtype=float))
    if recovered.shape[1] != model.ell.size:
        raise ValueError(
            f"recovered_per_seed: {recovered.shape[1]} multipoles, expected {model.ell.size}"
        )
    estimates = np.array([linear_r_estimate(row, model, r_input) for row in recovered])
    n_seeds = estimates.size
    mean = float(estimates.mean())
    std = float(estimates.std(ddof=1)) if n_seeds > 1 else float("nan")
    sem = std / np.sqrt(n_seeds) if n_seeds > 1 else float("nan")
    verdict = None
    if n_seeds >= MIN_SEEDS_FOR_VERDICT:
        verdict = bool(abs(mean - r_input) <= N_SIGMA * sem)
    c_mod = model.c_mod(r_input)
    rows = []
    for first, last in bins(model.lmin, model.lmax):
        where = (model.ell >= first) & (model.ell <= last)
        modes = 2 * model.ell[where] + 1.0
        data_bb, data_sem = _bin_mean_sem(recovered[:, where], modes)
        model_bb = float(np.sum(modes * c_mod[where]) / modes.sum())
        rows.append(
            {
                "ell": [int(first), int(last)],
                "model_bb_k2": model_bb,
                "data_bb_k2": data_bb,
                "data_bb_sem_k2": data_sem,
                "data_over_model": data_bb / model_bb,
            }
        )
    return {
        "definition": "r read on the HILC's CMB map (recovered CMB + noise + foreground "
        "residual, no input subtracted) by one Newton step of the likelihood from r_input "
        "(likelihood.linear_r_estimate), per seed; consistent when the mean over seeds is "
        f"within {N_SIGMA:g} standard errors of r_input",
        "r_input": float(r_input),
        "r_per_seed": estimates.tolist(),
        "r_mean": mean,
        "r_sem": sem,
        "r_std_over_seeds": std,
        "sigma_r_fisher_at_r_input": model.fisher_sigma_r(r_input),
        "pull": (mean - r_input) / sem if n_seeds > 1 and sem > 0 else float("nan"),
        "n_seeds": int(n_seeds),
        "consistent": verdict,
        "bins": rows,
    }


def compare_model_with_data(
    settings: dict, model_noise, data_noise, residuals, model_noise_per_seed=None
) -> tuple[dict, np.ndarray, np.ndarray]:
    """(:func:`consistency.check_model`, the model's T_ell, the data's T_ell) of the
    analysis ``settings`` (config likelihood) with its model from the noise table
    ``model_noise`` and the data's transfer from ``data_noise`` (the same table when model
    and data come from the same seeds); ``model_noise_per_seed`` given (other seeds than
    the data's), the model's own errors are added: its N + C_FGres per seed and, when
    the analysis carries the transfer, that transfer's error."""
    analysis, lmax = settings["model"], settings["lmax"]
    model_transfer = analysis_transfer(model_noise, lmax, analysis)
    # what the data's map holds of the sky: its power transfer where the run measured it
    # (the recovered CMB's own BB), else (older runs) the B-to-B transfer
    power = "sky_power_transfer_bb" if "sky_power_transfer_bb" in data_noise else "sky_transfer_bb"
    errors = {}
    if model_noise_per_seed is not None:
        errors["model_noise_per_seed"] = model_noise_per_seed
        if model_transfer is not None:
            column = "sky_power_transfer_bb" if analysis == "recovered_power" else "sky_transfer_bb"
            errors["model_transfer_sem"] = model_noise[f"{column}_sem"].to_numpy()[: lmax + 1]
    if model_transfer is None:
        model_transfer = np.ones(lmax + 1)
    data_transfer = data_noise[power].to_numpy()[: lmax + 1]
    check = check_model(
        model_from_noise_table(model_noise, settings["lmin"], lmax, "paper_recipe"),
        model_transfer,
        data_transfer,
        data_noise[f"{power}_sem"].to_numpy()[: lmax + 1],
        residuals,
        **errors,
    )
    check["data_transfer"] = power
    return check, model_transfer, data_transfer


def held_out_splits(nosys_tables: list) -> list[tuple[str, list, list]]:
    """[(name, the seeds the model is measured on, the seeds it is checked on)]: the seeds
    at even and at odd positions, both ways."""
    even, odd = nosys_tables[0::2], nosys_tables[1::2]
    return [("even -> odd", even, odd), ("odd -> even", odd, even)]


def held_out_check(config: dict, nosys_tables: list[pd.DataFrame]) -> dict | None:
    """The model check with the model measured on other seeds than the data: the seeds
    split into even and odd positions, the noise model (N_ell, C_FGres, the sky's
    transfer) of each half checked against the other half's residuals and transfer
    (:func:`check_model` with both halves' standard errors), both ways.
    Unlike the check on all seeds, where the model's N_ell is the mean of the residuals
    it is compared with, this one can fail when the seeds do not share one noise model
    (e.g. a seed-dependent leak) or its scatter is underestimated. None below 4 seeds."""
    if len(nosys_tables) < 4:
        return None
    settings = config["likelihood"]
    analysis, lmax = settings["model"], settings["lmax"]
    results = []
    for name, model_half, data_half in held_out_splits(nosys_tables):
        check, _, _ = compare_model_with_data(
            settings,
            measure(model_half),
            measure(data_half),
            [residual_bb(table, analysis, lmax) for table in data_half],
            model_noise_per_seed=[
                table["bb_residual_k2"].to_numpy()[: lmax + 1] for table in model_half
            ],
        )
        results.append(
            {
                "model_from_data": name,
                "consistent": check["consistent"],
                "failing_bins": check["failing_bins"],
                "data_over_model": [row["data_over_model"] for row in check["bins"]],
            }
        )
    return {
        "definition": "the model check with the noise model and transfer measured on half "
        "the seeds (even or odd positions) and the data of the other half, both ways, the "
        "two halves' standard errors combined",
        "bins": [row["ell"] for row in check["bins"]],
        "consistent": all(result["consistent"] for result in results),
        "splits": results,
    }


def r_recovery_check(config: dict, noise: pd.DataFrame, nosys_tables) -> dict | None:
    """:func:`check_r_recovery` of the input CMB's r (simulation.cmb_r) on the
    no-systematics HILC map of every seed, for the model without transfer (paper_recipe,
    paper_literal) and with the measured one (transfer_in_model), keyed by analysis. None
    when the spectra have no recovered-map column (made by an older component_separation).
    """
    if not all("bb_recovered_k2" in table for table in nosys_tables):
        return None
    settings = config["likelihood"]
    lmax = settings["lmax"]
    recovered = np.array(
        [table["bb_recovered_k2"].to_numpy()[: lmax + 1] for table in nosys_tables]
    )
    results = {}
    for analysis in ANALYSES:
        if analysis == "recovered_power" and "cmb_leakage_bb_k2" not in noise:
            continue
        model = model_from_noise_table(noise, settings["lmin"], lmax, analysis)
        results[analysis] = check_r_recovery(model, recovered, config["simulation"]["cmb_r"])
        log.debug(
            "r recovered on the HILC map with the %s model: %.3e +- %.3e (input %.3e)%s",
            analysis,
            results[analysis]["r_mean"],
            results[analysis]["r_sem"],
            config["simulation"]["cmb_r"],
            "" if results[analysis]["consistent"] is not False else ": NOT consistent",
        )
    return results


def held_out_r_recovery(config: dict, nosys_tables: list[pd.DataFrame]) -> dict | None:
    """:func:`r_recovery_check` with the model measured on other seeds than the maps: the
    seeds split into even and odd positions, r read on each half's maps with the other
    half's noise model, both ways, keyed by analysis. On the seeds the model was measured
    on, the read-back is zero by construction to first order (the model's every term is
    their mean); across halves it tests that the model describes maps it was not made
    from. The standard error adds the model half's: that of the mean r its own seeds read
    on it. Per analysis: the first split's ``r_mean``, ``r_sem``, ``pull``, consistent
    when both splits are, and ``splits``. None below 8 seeds (4 per half) or without the
    recovered map's column."""
    if len(nosys_tables) < 2 * MIN_SEEDS_FOR_VERDICT:
        return None
    splits = []
    for name, model_half, data_half in held_out_splits(nosys_tables):
        noise = measure(model_half)
        on_data = r_recovery_check(config, noise, data_half)
        on_model = r_recovery_check(config, noise, model_half)
        if on_data is None or on_model is None:
            return None
        splits.append((name, on_data, on_model))
    results = {}
    for analysis in splits[0][1]:
        rows = []
        for name, on_data, on_model in splits:
            data, model = on_data[analysis], on_model[analysis]
            sem = float(np.hypot(data["r_sem"], model["r_sem"]))
            pull = (data["r_mean"] - data["r_input"]) / sem if sem > 0 else float("nan")
            rows.append(
                {
                    **data,
                    "model_from_data": name,
                    "r_sem_data": data["r_sem"],
                    "r_sem": sem,
                    "pull": pull,
                    "consistent": bool(abs(pull) <= N_SIGMA),
                }
            )
        first = rows[0]
        results[analysis] = {
            "definition": "r read on each half's no-systematics HILC maps (even or odd seed "
            "positions) with the model measured on the other half (r_recovery_check), both "
            "ways; r_sem: the data half's and the model half's standard errors in "
            f"quadrature; consistent when both splits are within {N_SIGMA:g} of them",
            "r_input": first["r_input"],
            "r_mean": first["r_mean"],
            "r_sem": first["r_sem"],
            "pull": first["pull"],
            "sigma_r_fisher_at_r_input": first["sigma_r_fisher_at_r_input"],
            "consistent": all(row["consistent"] for row in rows),
            "splits": rows,
        }
        log.info(
            "r read back on held-out maps with the %s model: %s (input %.3e)",
            analysis,
            "; ".join(f"{row['r_mean']:.3e} +- {row['r_sem']:.1e}" for row in rows),
            first["r_input"],
        )
    return results


def information_and_bias(model: BBModel, c_sys: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """(the Fisher information on r per ell, the Fisher bias per ell of the systematic BB
    ``c_sys``, their fractions per bin of :func:`bins`) from the analysis's ``model``."""
    information = fisher_information_per_ell(model)
    bias = fisher_bias_per_ell(c_sys, model)
    rows = []
    for first, last in bins(model.lmin, model.lmax):
        where = (model.ell >= first) & (model.ell <= last)
        rows.append(
            {
                "ell": [int(first), int(last)],
                "information_fraction": float(information[where].sum() / information.sum()),
                "bias_fraction": float(bias[where].sum() / bias.sum()) if bias.sum() else 0.0,
            }
        )
    distribution = {
        "definition": "per bin: the fraction of the Fisher information 1 / sigma_r^2 and of "
        "the Fisher bias of the mean systematic BB (sigma_g1 = 1), from the analysis's model",
        "sigma_r_fisher": model.fisher_sigma_r(0.0),
        "bins": rows,
    }
    return information, bias, distribution
