"""The bias one instrument carries: g1 draws held fixed over every sky and noise draw.

The study draws new g1 for every seed (:func:`systematics.unit_g1_draws`), so the term
linear in g1, C_obs(sigma) = C_nosys + 2 sigma C_cross + sigma^2 C_auto with C_cross the
cross spectrum of the systematic (at sigma_g1 = 1 1/K) with the no-systematics residual,
averages to zero over seeds. A real focal plane has one set of g1: over skies and noise
its linear term averages to E[C_cross | z], which is zero only if nothing in the
residual correlates with that instrument's systematic (the foreground residual and the
dipole's template are every seed's; the template's noise x h part is drawn with the
noise). For each fixed instrument i (:func:`systematics.instrument_g1_draws`) the
Fisher bias (:func:`likelihood.fisher_bias`) of the seeds' mean spectra gives

    delta r_i(sigma) = 2 sigma b_i + sigma^2 k_i,
    b_i = F[mean_s C_cross,i,s],  k_i = F[mean_s C_auto,i,s],

and the requirement of instrument i is the smallest sigma with |delta r_i| = budget
(:func:`budget_sigma`). b_i is measured to +- its standard error over seeds: a b_i
consistent with zero means the instrument's linear term is below what the seeds
resolve, and the requirement then bounds rather than measures it (|b_i| includes that
error; ``requirement_debiased_per_k`` uses sqrt(max(b_i^2 - se_i^2, 0))). The
per-seed scatter of 2 sigma b_i,s is not a bias: it widens r like noise (beside sigma_r).

The paper's convention, the shift of the 68 % point of L(r), is linear in the added
spectrum wherever the budget is small beside sigma_r (the likelihood's linear regime):
delta r_68(sigma) = 2 sigma b68_i + sigma^2 k68_i, each coefficient one numerical shift
of the 68 % point (:func:`likelihood.fraction_point_shift`) of the seeds' mean
no-systematics residual (:func:`fraction_point_terms`); the same budget crossing follows.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import scipy.stats

from .likelihood import fisher_bias, fraction_point_shift

log = logging.getLogger(__name__)

CROSS = "bb_cross_instrument{index}_k3"
CROSS_UNFILTERED = "bb_cross_unfiltered_instrument{index}_k3"
AUTO = "bb_auto_instrument{index}_k4"
COMMON = "common_offset"
COMMON_MITIGATED = "common_offset_mitigated"  # what the template fit leaves of it


def common_columns(name: str = COMMON) -> tuple[str, str, str]:
    """The columns (auto, cross, cross_unfiltered) of a common offset ``name`` in the
    seeds' tables (:meth:`SeedMaps.instrument_spectra`)."""
    return f"bb_auto_{name}_k4", f"bb_cross_{name}_k3", f"bb_cross_unfiltered_{name}_k3"


COMMON_AUTO, COMMON_CROSS, COMMON_CROSS_UNFILTERED = common_columns()


def n_instruments(table: pd.DataFrame) -> int:
    """The number of instruments in a table of :meth:`SeedMaps.instrument_spectra`."""
    return sum(1 for column in table.columns if column.startswith("bb_auto_instrument"))


def budget_sigma(b: float, k: float, budget: float) -> float:
    """The smallest sigma > 0 [1/K] with |2 sigma b + sigma^2 k| = budget (k >= 0):
    (-b + sqrt(b^2 + k B)) / k when delta r rises through +B first; when b < 0 and the
    dip, -b^2 / k, reaches -B: (-b - sqrt(b^2 - k B)) / k; with k = 0, B / 2|b| (inf
    if b = 0 too: nothing left of the systematic)."""
    b, k, budget = float(b), float(k), float(budget)
    if not (k >= 0 and budget > 0):
        raise ValueError(f"k = {k}, budget = {budget}: expected k >= 0 and budget > 0")
    if k == 0:
        return budget / (2 * abs(b)) if b != 0 else float("inf")
    if b < 0 and b * b >= k * budget:
        return (-b - np.sqrt(b * b - k * budget)) / k
    return (-b + np.sqrt(b * b + k * budget)) / k


def _column(index: int, unfiltered: bool) -> str:
    return (CROSS_UNFILTERED if unfiltered else CROSS).format(index=index)


def instrument_biases(tables: list[pd.DataFrame], model, unfiltered: bool = False) -> list[dict]:
    """Per instrument: b (mean over seeds of the linear term's Fisher bias, per 1/K), its
    standard error, the seeds' scatter b_std, and k [K^2] (the quadratic term's), from
    the seeds' tables (:meth:`SeedMaps.instrument_spectra`) through ``model``.
    ``unfiltered``: the cross spectrum with the residual against the unfiltered CMB (the
    paper_literal analysis)."""
    if not tables:
        raise ValueError("fixed instruments: no seed's table")
    counts = {n_instruments(table) for table in tables}
    if len(counts) != 1:
        raise ValueError(f"fixed instruments: the seeds' tables hold {sorted(counts)} instruments")
    return [
        {
            "instrument": index,
            **_bias(tables, model, _column(index, unfiltered), AUTO.format(index=index)),
        }
        for index in range(counts.pop())
    ]


def _bias(tables: list[pd.DataFrame], model, cross: str, auto: str) -> dict:
    """b (mean over seeds of the Fisher bias of the column ``cross``, per 1/K), its
    standard error and scatter over seeds, and k (of the column ``auto``) [K^2]."""
    size = model.ell.size
    b_seeds = np.array([fisher_bias(t[cross].to_numpy()[:size], model) for t in tables])
    k_seeds = np.array([fisher_bias(t[auto].to_numpy()[:size], model) for t in tables])
    several = b_seeds.size > 1
    return {
        "b_per_k": float(b_seeds.mean()),
        "b_error_per_k": float(b_seeds.std(ddof=1) / np.sqrt(b_seeds.size))
        if several
        else float("nan"),
        "b_std_over_seeds_per_k": float(b_seeds.std(ddof=1)) if several else float("nan"),
        "k_per_k2": float(k_seeds.mean()),
        "n_seeds": int(b_seeds.size),
    }


def common_offset_estimator(
    tables: list[pd.DataFrame],
    model,
    budget: float,
    k_random: float,
    unfiltered: bool = False,
    name: str = COMMON,
) -> dict | None:
    """The requirement on a g1 common to every detector of the systematics channels, mu
    (a residual the calibration shares; :meth:`SeedMaps.common_offset_draws`): delta r =
    2 mu b + mu^2 k from the seeds' ``common_offset`` columns, |mu| < :func:`budget_sigma`
    of |b| (the sign of mu is not known: the sign that adds the linear term to the
    quadratic one reaches the budget first);
    and the region allowed with the random population of spread sigma beside it (Fisher
    bias ``k_random`` sigma^2; the cross term of a zero-mean draw with mu averages out):
    k_random sigma^2 + 2 mu |b| + mu^2 k <= budget, given as the largest |mu| at a few
    sigma, with |b| debiased by its standard error over seeds (sqrt(max(b^2 - se^2, 0)): a
    b the seeds do not resolve does not set the region). ``name``: the tables' columns
    ``bb_auto_<name>_k4`` and ``bb_cross[_unfiltered]_<name>_k3`` (COMMON, or
    COMMON_MITIGATED: the same after the template fit, with ``k_random`` the random
    population's after it). None when the tables hold no such columns."""
    auto, cross, cross_unfiltered = common_columns(name)
    if not tables or auto not in tables[0]:
        return None
    row = _bias(tables, model, cross_unfiltered if unfiltered else cross, auto)
    b, error = row["b_per_k"], row["b_error_per_k"]
    k = max(row["k_per_k2"], 0.0)  # below 0 only at rounding (a template fitted away whole)
    debiased = np.sqrt(max(b * b - error * error, 0.0)) if error > 0 else abs(b)
    sigma_required = float(np.sqrt(budget / k_random)) if k_random > 0 else float("inf")
    region = []
    for fraction in (0.0, 0.5, 0.8, 0.95):
        left = budget * (1.0 - fraction**2)  # what the random population leaves of the budget
        region.append(
            {"sigma_over_requirement": fraction, "mu_max_per_k": budget_sigma(debiased, k, left)}
        )
    return {
        "definition": "g1 = mu on every detector of the systematics channels, the same for "
        "every seed: delta r = 2 mu b + mu^2 k (Fisher peak shift of the seeds' mean cross "
        "and auto spectra through the no-systematics weights); with a random population of "
        "spread sigma beside it, k_random sigma^2 + 2 mu b + mu^2 k <= budget",
        **row,
        "t_linear": b / error if error > 0 else float("nan"),
        "requirement_mu_per_k": budget_sigma(abs(b), k, budget),
        "requirement_mu_debiased_per_k": budget_sigma(debiased, k, budget),
        "requirement_mu_quadratic_only_per_k": float(np.sqrt(budget / k))
        if k > 0
        else float("inf"),
        "k_over_k_random": k / k_random if k_random > 0 else float("nan"),
        "random_requirement_sigma_per_k": sigma_required,
        "allowed_region": region,
    }


def fraction_point_terms(
    tables: list[pd.DataFrame],
    c_res_nosys,
    model,
    unfiltered: bool = False,
    sigma_ref: float = 1e-3,
) -> tuple[list[tuple[float, float]], float]:
    """([(b68, k68) per instrument], linearity): the 68 %-point shift's coefficients,
    delta r_68(sigma) = 2 sigma b68 + sigma^2 k68, of the seeds' mean cross and auto
    spectra added to ``c_res_nosys`` (the seeds' mean no-systematics residual), each the
    shift at ``sigma_ref`` [1/K] divided by 2 sigma_ref or sigma_ref^2. ``linearity``:
    instrument 0's linear shift at 3 sigma_ref over 3 times its shift at sigma_ref (1 in
    the linear regime this rests on)."""
    size = model.ell.size
    terms, linearity = [], float("nan")
    for index in range(n_instruments(tables[0])):
        cross = np.mean([t[_column(index, unfiltered)].to_numpy()[:size] for t in tables], axis=0)
        auto = np.mean([t[AUTO.format(index=index)].to_numpy()[:size] for t in tables], axis=0)
        (linear,) = fraction_point_shift(c_res_nosys, 2 * sigma_ref * cross, model, [1.0])
        (quadratic,) = fraction_point_shift(c_res_nosys, auto, model, [sigma_ref])
        terms.append((float(linear / (2 * sigma_ref)), float(quadratic / sigma_ref**2)))
        if index == 0:
            (tripled,) = fraction_point_shift(  # 3 times the added spectrum
                c_res_nosys, 2 * sigma_ref * cross, model, [np.sqrt(3.0)]
            )
            linearity = tripled / (3 * linear) if linear else float("nan")
    return terms, linearity


def split_half_correlation(tables: list[pd.DataFrame], model, unfiltered: bool = False) -> dict:
    """Whether the instruments' linear terms are real: b_i from the even seeds against b_i
    from the odd seeds, Pearson's correlation over the instruments and its two-sided p
    value (a linear term the seeds resolve correlates; estimation noise does not). NaN
    with fewer than four seeds or three instruments."""
    result = {"pearson_r": float("nan"), "p_value": float("nan"), "halves": "even, odd seeds"}
    if len(tables) < 4 or n_instruments(tables[0]) < 3:
        return result
    even, odd = (
        np.array([row["b_per_k"] for row in instrument_biases(half, model, unfiltered)])
        for half in (tables[0::2], tables[1::2])
    )
    test = scipy.stats.pearsonr(even, odd)
    result.update(pearson_r=float(test.statistic), p_value=float(test.pvalue))
    return result


def fixed_instrument_estimator(
    tables: list[pd.DataFrame],
    model,
    budget: float,
    unfiltered: bool = False,
    c_res_nosys=None,
) -> dict:
    """The requirement of each fixed instrument (:func:`budget_sigma` of its b and k),
    beside its quadratic term alone, and their spread over instruments; with
    ``c_res_nosys`` (the seeds' mean no-systematics residual) the same in the paper's
    68 %-point convention (:func:`fraction_point_terms`)."""
    rows = instrument_biases(tables, model, unfiltered)
    for row in rows:
        b, error, k = row["b_per_k"], row["b_error_per_k"], row["k_per_k2"]
        row["t_linear"] = b / error if error > 0 else float("nan")
        row["requirement_sigma_g1_per_k"] = budget_sigma(b, k, budget)
        debiased = np.sign(b) * np.sqrt(max(b * b - error * error, 0.0)) if error > 0 else b
        row["requirement_debiased_per_k"] = budget_sigma(debiased, k, budget)
        row["requirement_quadratic_only_per_k"] = float(np.sqrt(budget / k))
    fraction_point = None
    if c_res_nosys is not None:
        terms, linearity = fraction_point_terms(tables, c_res_nosys, model, unfiltered)
        for row, (b68, k68) in zip(rows, terms, strict=True):
            t = row["t_linear"]
            debiased = (  # b68's error is b68 / t, the Fisher term's relative error
                np.sign(b68) * np.sqrt(max(b68 * b68 * (1 - 1 / t**2), 0.0))
                if np.isfinite(t) and t != 0
                else b68
            )
            row["b68_per_k"], row["k68_per_k2"] = b68, k68
            row["requirement_68_per_k"] = budget_sigma(b68, k68, budget)
            row["requirement_68_debiased_per_k"] = budget_sigma(debiased, k68, budget)
            row["requirement_68_quadratic_only_per_k"] = float(np.sqrt(budget / k68))
        fraction_point = {
            "definition": "the same in the paper's convention: delta r_68 = 2 sigma b68 + "
            "sigma^2 k68, the shifts of the 68 % point of L(r) for the seeds' mean spectra "
            "(linear regime: budget << sigma_r); debiased with the Fisher term's t",
            "linearity_check": linearity,
            **{
                f"{name}_median_per_k": float(np.median([row[key] for row in rows]))
                for name, key in (
                    ("requirement", "requirement_68_per_k"),
                    ("requirement_debiased", "requirement_68_debiased_per_k"),
                    ("quadratic_only", "requirement_68_quadratic_only_per_k"),
                )
            },
        }
    with_linear = np.array([row["requirement_sigma_g1_per_k"] for row in rows])
    debiased = np.array([row["requirement_debiased_per_k"] for row in rows])
    quadratic = np.array([row["requirement_quadratic_only_per_k"] for row in rows])
    t = np.array([row["t_linear"] for row in rows])
    k_mean = float(np.mean([row["k_per_k2"] for row in rows]))
    return {
        "definition": "g1 draws held fixed over every seed (one focal plane each); per "
        "instrument delta r = 2 sigma b + sigma^2 k (Fisher peak shift of the seeds' mean "
        "cross and auto spectra through the no-systematics weights); requirement: the "
        "smallest sigma_g1 with |delta r| = budget",
        "n_instruments": len(rows),
        "residual": "unfiltered CMB" if unfiltered else "filtered CMB reference",
        "requirement_median_per_k": float(np.median(with_linear)),
        "requirement_16_84_per_k": np.percentile(with_linear, [16, 84]).tolist(),
        "requirement_debiased_median_per_k": float(np.median(debiased)),
        "quadratic_only_median_per_k": float(np.median(quadratic)),
        "quadratic_only_of_mean_k_per_k": float(np.sqrt(budget / k_mean)),
        "fraction_linear_resolved": float(np.mean(np.abs(t) > 2.0)),
        "chi2_linear": float(np.sum(t**2)),
        "linear_split_half": split_half_correlation(tables, model, unfiltered),
        "fraction_point": fraction_point,
        "instruments": rows,
    }


def delta_r_curves(rows: list[dict], sigma) -> np.ndarray:
    """(n_instruments, n_sigma) |2 sigma b_i + sigma^2 k_i| on the grid ``sigma`` [1/K]."""
    sigma = np.asarray(sigma, dtype=float)
    b = np.array([row["b_per_k"] for row in rows])[:, None]
    k = np.array([row["k_per_k2"] for row in rows])[:, None]
    return np.abs(2 * sigma * b + sigma**2 * k)


def fixed_instruments_summary(
    tables: list[pd.DataFrame], model, budget: float, analysis: str, c_res_nosys=None
) -> dict | None:
    """:func:`fixed_instrument_estimator` of the seeds' instrument ``tables`` (None without
    instruments), logged; with ``c_res_nosys``, the seeds' mean no-systematics residual BB,
    also in the paper's 68 %-point convention."""
    if not tables or n_instruments(tables[0]) == 0:
        return None
    unfiltered = analysis == "paper_literal"
    fixed = fixed_instrument_estimator(tables, model, budget, unfiltered, c_res_nosys)
    log.info(
        "fixed instruments (%d, %d seeds): requirement with the linear term median %.3e "
        "1/K (16-84 %%: %.3e-%.3e), own power alone %.3e; linear term resolved (|t| > 2) "
        "in %.0f %% of the instruments, even/odd seeds' b correlate by r = %.2f (p %.2g)",
        fixed["n_instruments"],
        len(tables),
        fixed["requirement_median_per_k"],
        *fixed["requirement_16_84_per_k"],
        fixed["quadratic_only_median_per_k"],
        100 * fixed["fraction_linear_resolved"],
        fixed["linear_split_half"]["pearson_r"],
        fixed["linear_split_half"]["p_value"],
    )
    if fixed["fraction_point"] is not None:
        log.info(
            "fixed instruments, 68 %% point: median %.3e (debiased %.3e), own power alone "
            "%.3e 1/K; linearity %.4f",
            fixed["fraction_point"]["requirement_median_per_k"],
            fixed["fraction_point"]["requirement_debiased_median_per_k"],
            fixed["fraction_point"]["quadratic_only_median_per_k"],
            fixed["fraction_point"]["linearity_check"],
        )
    return fixed
