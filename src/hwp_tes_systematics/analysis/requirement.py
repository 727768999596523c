"""Bias on r versus sigma_g1 and the requirement on sigma_g1 (Micheli et al. 2024, Sec. 4).

For each sigma_g1 [1/K] and seed the bias is delta r = |r_sys - r_nosys| (the 68 % points
of the likelihood with and without systematics, :mod:`likelihood`); its mean over seeds
is fitted with

    mean delta r = k sigma_g1^2                                  (quadratic, k [K^2])
    mean delta r = A sigma_g1^alpha                              (free power law, check alpha ~ 2)

and the requirement is the sigma_g1 at which the quadratic reaches the budget,

    sigma_req = sqrt(budget / k)       [1/K]   (budget: 6.5e-6, LiteBIRD's allocation).

Both fits are done in log space, ln(delta r) = ln k + 2 ln sigma (resp. ln A + alpha
ln sigma), where the points span several decades with comparable relative errors; a
linear-space least squares would be dominated by the largest sigma. Points with
sigma <= 0 (the no-systematics reference) are dropped; points with a non-positive or
non-finite mean delta r are dropped with a warning; fewer than 2 usable points raise
ValueError.

Two estimators (:func:`delta_r_table`): the paper's delta r = |r_sys - r_nosys| and the
systematic-only k_seed sigma^2 (the Fisher bias of the systematic through the
no-systematics HILC weights, :mod:`ilc_residuals`). The paper's is assessed by
:func:`assess_quadratic_regime` and its grid extended downwards from the maps when fewer
than two points are quadratic (:func:`paper_estimator`); the systematic-only one gives
its requirement and scatter over seeds per HWPSS scale (:mod:`.systematic_only`).

Caveat (see the tests): delta r is exactly quadratic in sigma_g1 only while the
systematic power is a small perturbation, delta r << sigma_r (Fisher width of r). For
larger biases the 68 % point grows faster than the excess power (the cosmic variance of
the tensor modes widens the likelihood), and the fitted exponent exceeds 2.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Mapping

import numpy as np
import pandas as pd

from .ilc_residuals import SeedMaps
from .likelihood import fit_r_common_grid
from .noise_model import residual_bb
from .systematics import NOSYS

log = logging.getLogger(__name__)

DELTA_R_BUDGET = 6.5e-6  # allocated systematic error budget on r per effect (paper, PTEP)
SUMMARY_COLUMNS = ("sigma_g1", "mean_delta_r", "std_delta_r", "sem_delta_r", "n_seeds")


def delta_r(r_sys, r_nosys):
    """delta r = |r_sys - r_nosys| (dimensionless), elementwise."""
    return np.abs(np.asarray(r_sys, dtype=float) - np.asarray(r_nosys, dtype=float))


def summarise(delta_r_table) -> pd.DataFrame:
    """Per sigma_g1: mean, standard deviation, standard error of delta r over seeds, and count.

    ``delta_r_table``: a DataFrame with columns ``sigma_g1`` and ``delta_r`` (one row per
    sigma_g1 and seed; other columns ignored), or a mapping {sigma_g1: sequence of delta r}.
    Returns a DataFrame sorted by sigma_g1 with columns ``sigma_g1`` [1/K],
    ``mean_delta_r``, ``std_delta_r`` (sample standard deviation, ddof = 1; NaN for one
    seed), ``sem_delta_r`` = std / sqrt(n_seeds) and ``n_seeds``. Non-finite delta r
    are dropped (with a warning).
    """
    if isinstance(delta_r_table, pd.DataFrame):
        missing = {"sigma_g1", "delta_r"} - set(delta_r_table.columns)
        if missing:
            raise ValueError(f"delta_r_table: missing columns {sorted(missing)}")
        table = delta_r_table[["sigma_g1", "delta_r"]].astype(float)
    elif isinstance(delta_r_table, Mapping):
        rows = [
            (float(sigma), float(value))
            for sigma, values in delta_r_table.items()
            for value in np.atleast_1d(np.asarray(values, dtype=float))
        ]
        table = pd.DataFrame(rows, columns=["sigma_g1", "delta_r"])
    else:
        raise TypeError("delta_r_table: expected a DataFrame or a {sigma_g1: values} mapping")
    finite = np.isfinite(table["delta_r"]) & np.isfinite(table["sigma_g1"])
    if not finite.all():
        warnings.warn(
            f"summarise: {int((~finite).sum())} non-finite rows dropped", RuntimeWarning, 2
        )
        table = table[finite]
    if table.empty:
        raise ValueError("delta_r_table: no finite delta r")
    grouped = table.groupby("sigma_g1", sort=True)["delta_r"]
    summary = pd.DataFrame(
        {
            "mean_delta_r": grouped.mean(),
            "std_delta_r": grouped.std(ddof=1),
            "n_seeds": grouped.count().astype(int),
        }
    ).reset_index()
    summary["sem_delta_r"] = summary["std_delta_r"] / np.sqrt(summary["n_seeds"])
    return summary[list(SUMMARY_COLUMNS)]


def _usable(sigma, mean_delta_r, weights=None, caller: str = "fit"):
    """(sigma, mean, weights) restricted to sigma > 0 and finite mean delta r > 0."""
    sigma = np.asarray(sigma, dtype=float).ravel()
    mean_delta_r = np.asarray(mean_delta_r, dtype=float).ravel()
    if sigma.shape != mean_delta_r.shape:
        raise ValueError(f"{caller}: sigma {sigma.shape} and delta r {mean_delta_r.shape} differ")
    if weights is None:
        weights = np.ones_like(sigma)
    else:
        weights = np.asarray(weights, dtype=float).ravel()
        if weights.shape != sigma.shape:
            raise ValueError(f"{caller}: weights {weights.shape} and sigma {sigma.shape} differ")
    keep = np.isfinite(sigma) & (sigma > 0)  # sigma = 0: the no-systematics reference
    bad = keep & ~(np.isfinite(mean_delta_r) & (mean_delta_r > 0))
    if bad.any():
        warnings.warn(
            f"{caller}: {int(bad.sum())} point(s) with non-positive or non-finite mean delta r "
            f"excluded (sigma_g1 = {sigma[bad].tolist()})",
            RuntimeWarning,
            stacklevel=3,
        )
    keep &= ~bad
    bad_weight = keep & ~(np.isfinite(weights) & (weights > 0))
    if bad_weight.any():
        warnings.warn(
            f"{caller}: {int(bad_weight.sum())} point(s) with non-positive or non-finite "
            "weight excluded",
            RuntimeWarning,
            stacklevel=3,
        )
    keep &= ~bad_weight
    if np.count_nonzero(keep) < 2:
        raise ValueError(
            f"{caller}: {np.count_nonzero(keep)} usable point(s) (sigma_g1 > 0 and finite mean "
            "delta r > 0); at least 2 are needed"
        )
    return sigma[keep], mean_delta_r[keep], weights[keep]


def log_weights_from_sem(mean_delta_r, sem_delta_r) -> np.ndarray:
    """Weights for the log-space fits: 1 / var(ln mean) ~ (mean / sem)^2 (first order)."""
    mean_delta_r = np.asarray(mean_delta_r, dtype=float)
    sem_delta_r = np.asarray(sem_delta_r, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (mean_delta_r / sem_delta_r) ** 2


def fit_quadratic(sigma, mean_delta_r, weights=None) -> float:
    """k [K^2] of mean delta r = k sigma^2 (sigma in 1/K), by weighted least squares in log space.

    ln(mean delta r) = ln k + 2 ln sigma with the exponent fixed at 2, so

        ln k = sum w_i [ln(delta r_i) - 2 ln(sigma_i)] / sum w_i.

    ``weights``: w_i, inverse variances of ln(delta r_i) (e.g. :func:`log_weights_from_sem`,
    (mean / sem)^2); default equal weights (equal relative errors). Exact on exact
    quadratic data. sigma <= 0 and non-positive delta r are excluded (see the module).
    """
    sigma, mean_delta_r, weights = _usable(sigma, mean_delta_r, weights, "fit_quadratic")
    log_k = np.sum(weights * (np.log(mean_delta_r) - 2.0 * np.log(sigma))) / np.sum(weights)
    return float(np.exp(log_k))


def fit_power_law(sigma, mean_delta_r) -> tuple[float, float, float]:
    """(A, alpha, sigma_alpha) of mean delta r = A sigma^alpha, ordinary least squares in log-log.

    ln(delta r) = ln A + alpha ln sigma; sigma_alpha = sqrt(s^2 / S_xx), with
    s^2 = RSS / (n - 2) the residual variance and S_xx = sum (ln sigma - mean)^2 (the
    scatter of the points about the line, not the seed-to-seed error bars): NaN for
    n = 2 points. A is in K^alpha if sigma is in 1/K.
    """
    sigma, mean_delta_r, _ = _usable(sigma, mean_delta_r, None, "fit_power_law")
    x, y = np.log(sigma), np.log(mean_delta_r)
    sxx = np.sum((x - x.mean()) ** 2)
    if sxx <= 0:
        raise ValueError("fit_power_law: at least 2 distinct sigma_g1 are needed")
    alpha = np.sum((x - x.mean()) * (y - y.mean())) / sxx
    log_a = y.mean() - alpha * x.mean()
    n = x.size
    if n > 2:
        rss = np.sum((y - log_a - alpha * x) ** 2)
        alpha_sigma = float(np.sqrt(rss / (n - 2) / sxx))
    else:
        alpha_sigma = float("nan")
    return float(np.exp(log_a)), float(alpha), alpha_sigma


def requirement_sigma(k: float, budget: float = DELTA_R_BUDGET) -> float:
    """sigma_g1 [1/K] at which k sigma^2 = budget: sqrt(budget / k) (k in K^2, k > 0)."""
    k, budget = float(k), float(budget)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"k = {k}: expected a finite k > 0")
    if not (np.isfinite(budget) and budget > 0):
        raise ValueError(f"budget = {budget}: expected a finite budget > 0")
    return float(np.sqrt(budget / k))


def _usable_points(sigma, mean_delta_r) -> tuple[np.ndarray, np.ndarray]:
    """The grid points with sigma > 0 and a finite, positive delta r, sorted by sigma."""
    sigma = np.asarray(sigma, dtype=float)
    mean_delta_r = np.asarray(mean_delta_r, dtype=float)
    keep = (sigma > 0) & np.isfinite(mean_delta_r) & (mean_delta_r > 0)
    order = np.argsort(sigma[keep])
    return sigma[keep][order], mean_delta_r[keep][order]


def budget_crossing(sigma, mean_delta_r, budget: float = DELTA_R_BUDGET) -> float:
    """The sigma_g1 [1/K] at which the measured curve first reaches the budget, model-free.

    Between the grid points sigma_i < sigma_j that bracket it (delta r_i < budget <=
    delta r_j), the curve is interpolated linearly in log-log:

        ln sigma_c = ln sigma_i + ln(budget / delta r_i) / alpha_ij,
        alpha_ij = ln(delta r_j / delta r_i) / ln(sigma_j / sigma_i).

    Points with sigma <= 0 or a non-positive or non-finite delta r are skipped. NaN when
    no pair brackets the budget (all points below it, or the first already above it).
    """
    sigma, mean_delta_r = _usable_points(sigma, mean_delta_r)
    x, y = np.log(sigma), np.log(mean_delta_r)
    target = np.log(float(budget))
    for i in range(len(x) - 1):
        if y[i] < target <= y[i + 1]:
            slope = (y[i + 1] - y[i]) / (x[i + 1] - x[i])
            return float(np.exp(x[i] + (target - y[i]) / slope))
    return float("nan")


def crossing_outside_grid(sigma, mean_delta_r, budget: float = DELTA_R_BUDGET) -> str | None:
    """Where the budget lies when :func:`budget_crossing` is NaN, in words; None otherwise.

    "below": the lowest sigma_g1 of the grid already reaches the budget, so the crossing
    (the requirement) is below it; "above": every point is under the budget.
    """
    if np.isfinite(budget_crossing(sigma, mean_delta_r, budget)):
        return None
    sigma, mean_delta_r = _usable_points(sigma, mean_delta_r)
    if sigma.size == 0:
        return "no positive mean delta r on the grid"
    if mean_delta_r[0] >= budget:
        return (
            f"below the grid: mean delta r is {mean_delta_r[0]:.3g} >= {budget:.3g} already "
            f"at the lowest sigma_g1, {sigma[0]:.3g} 1/K"
        )
    return (
        f"above the grid: mean delta r is {mean_delta_r[-1]:.3g} < {budget:.3g} at the "
        f"highest sigma_g1, {sigma[-1]:.3g} 1/K"
    )


def budget_crossing_over_seeds(table, budget: float = DELTA_R_BUDGET) -> dict:
    """:func:`budget_crossing` of the mean over seeds, and of each seed's own curve.

    ``table``: the delta r table (columns seed, sigma_g1, delta_r). Returns
    {"sigma_g1_per_k", "outside_grid", "per_seed_per_k", "std_over_seeds_per_k",
    "n_seeds_crossing"}; ``outside_grid`` (:func:`crossing_outside_grid`) says on which
    side of the grid the mean's crossing lies when it is NaN.
    """
    summary = summarise(table)
    mean_crossing = budget_crossing(summary["sigma_g1"], summary["mean_delta_r"], budget)
    per_seed = [
        budget_crossing(rows["sigma_g1"], rows["delta_r"], budget)
        for _, rows in table.groupby("seed")
    ]
    finite = [value for value in per_seed if np.isfinite(value)]
    return {
        "definition": "sigma_g1 where mean delta r reaches the budget, interpolated in "
        "log-log between the bracketing grid points (no model assumed)",
        "sigma_g1_per_k": mean_crossing,
        "outside_grid": crossing_outside_grid(summary["sigma_g1"], summary["mean_delta_r"], budget),
        "per_seed_per_k": per_seed,
        "std_over_seeds_per_k": float(np.std(finite, ddof=1)) if len(finite) > 1 else float("nan"),
        "n_seeds_crossing": len(finite),
    }


QUADRATIC_REGIME = 0.1  # mean delta r below this x sigma_r: the 68 % point is quadratic (measured)
EXPONENT_TOLERANCE = 0.2  # |alpha - 2| allowed beyond 3 sigma_alpha (and with 2 points)


def assess_quadratic_regime(sigma, mean_delta_r, sigma_r: float) -> dict:
    """Does mean delta r = k sigma^2 describe the points, and from which of them is k fitted?

    A point is in the quadratic regime when 0 < mean delta r < QUADRATIC_REGIME sigma_r
    (beyond, the 68 % point grows faster than the systematic's power). The free
    power-law exponent alpha is fitted on all points and on those of the regime; the
    sigma^2 model is consistent when the regime's alpha is within
    max(3 sigma_alpha, EXPONENT_TOLERANCE) of 2. ``valid`` = at least two points in the
    regime and a consistent exponent. k is fitted on the regime's points (all points
    when fewer than two are in it, with ``valid`` false). ``reason`` says why in words.
    """
    sigma = np.asarray(sigma, dtype=float)
    mean_delta_r = np.asarray(mean_delta_r, dtype=float)
    positive = (sigma > 0) & np.isfinite(mean_delta_r) & (mean_delta_r > 0)
    in_regime = positive & (mean_delta_r < QUADRATIC_REGIME * sigma_r)
    used = in_regime if in_regime.sum() >= 2 else positive
    k = fit_quadratic(sigma[used], mean_delta_r[used])
    _, alpha_all, alpha_all_sigma = fit_power_law(sigma[positive], mean_delta_r[positive])
    _, alpha, alpha_sigma = fit_power_law(sigma[used], mean_delta_r[used])
    tolerance = EXPONENT_TOLERANCE
    if np.isfinite(alpha_sigma):
        tolerance = max(tolerance, 3.0 * alpha_sigma)
    consistent = bool(abs(alpha - 2.0) <= tolerance)
    n_regime = int(in_regime.sum())
    valid = n_regime >= 2 and consistent
    if valid:
        reason = (
            f"{n_regime} points below {QUADRATIC_REGIME:g} sigma_r follow sigma^2 "
            f"(exponent {alpha:.2f})"
        )
    elif n_regime < 2:
        reason = (
            f"only {n_regime} point(s) below {QUADRATIC_REGIME:g} sigma_r = "
            f"{QUADRATIC_REGIME * sigma_r:.2g}: the quadratic regime is not reached"
        )
    else:
        error = f" +- {alpha_sigma:.2f}" if np.isfinite(alpha_sigma) else " (two points)"
        reason = (
            f"the points below {QUADRATIC_REGIME:g} sigma_r do not follow sigma^2: "
            f"exponent {alpha:.2f}{error}"
        )
    return {
        "k_per_k2": k,
        "sigma_g1_used_per_k": sigma[used].tolist(),
        "sigma_r_fisher": float(sigma_r),
        "quadratic_threshold_delta_r": QUADRATIC_REGIME * float(sigma_r),
        "sigma_g1_in_quadratic_regime_per_k": sigma[in_regime].tolist(),
        "free_exponent": alpha_all,
        "free_exponent_sigma": alpha_all_sigma,
        "free_exponent_fitted_points": alpha,
        "free_exponent_fitted_points_sigma": alpha_sigma,
        "sigma2_model_consistent": consistent,
        "valid": bool(valid),
        "reason": reason,
    }


def delta_r_table(likelihoods: list[dict]) -> pd.DataFrame:
    """One row per (seed, sigma): r_sys, r_nosys, both estimators' delta r."""
    rows = []
    for result in likelihoods:
        r_nosys = result["cases"][NOSYS]["r_fraction"]
        k_systematic = result["systematic_only"]["k_per_k2"]
        for case, values in result["cases"].items():
            if case == NOSYS:
                continue
            sigma = values["sigma_g1_per_k"]
            rows.append(
                {
                    "seed": result["seed"],
                    "case": case,
                    "sigma_g1": sigma,
                    "r_sys": values["r_fraction"],
                    "r_nosys": r_nosys,
                    "delta_r": abs(values["r_fraction"] - r_nosys),
                    "delta_r_systematic_only": k_systematic * sigma**2,
                    "sigma_r_fisher_0": result["sigma_r_fisher_0"],
                    "extended": False,
                }
            )
    return pd.DataFrame(rows).sort_values(["sigma_g1", "seed"], ignore_index=True)


def extra_delta_r(
    config, seed, sigmas, map_paths, nosys_spectra_csv, model, mask_path=None
) -> list[dict]:
    """The paper's delta r of one seed at sigmas outside the grid, from the channels' maps
    (or a_lm files on ``mask_path``, :meth:`SeedMaps.from_files`): the HILC at each sigma,
    its residual spectrum, and r with the no-systematics r on one grid."""
    seed_maps = SeedMaps.from_files(config, seed, map_paths, mask_path)
    lmax = model.lmax
    analysis = config["likelihood"]["model"]
    nosys = residual_bb(pd.read_csv(nosys_spectra_csv), analysis, lmax, nosys_spectra_csv)
    residuals = [residual_bb(seed_maps.residual_spectra(sigma), analysis, lmax) for sigma in sigmas]
    fraction = config["likelihood"]["fraction"]
    results = fit_r_common_grid([nosys, *residuals], model, fraction=fraction)
    r_nosys = results[0].r_fraction
    return [
        {
            "seed": seed,
            "case": f"extended {sigma:.1e}",
            "sigma_g1": sigma,
            "r_sys": result.r_fraction,
            "r_nosys": r_nosys,
            "delta_r": abs(result.r_fraction - r_nosys),
            "sigma_r_fisher_0": result.sigma_r_fisher_0,
            "extended": True,
        }
        for sigma, result in zip(sigmas, results[1:], strict=True)
    ]


def paper_estimator(table, config, extension) -> tuple[pd.DataFrame, dict]:
    """Extend the grid downwards until two points are quadratic (or the limit), then
    assess the regime; returns (table with the extended rows, assessment)."""
    sigma_r = float(table["sigma_r_fisher_0"].mean())
    for decade in range(config["requirement"]["max_extra_decades"] + 1):
        summary = summarise(table)
        regime = assess_quadratic_regime(summary["sigma_g1"], summary["mean_delta_r"], sigma_r)
        if len(regime["sigma_g1_in_quadratic_regime_per_k"]) >= 2 or extension is None:
            break
        if decade == config["requirement"]["max_extra_decades"]:
            break
        sigma_new = float(summary["sigma_g1"].min()) / 10.0
        log.info(
            "paper estimator: %s; adding sigma_g1 = %.1e (computed from the maps)",
            regime["reason"],
            sigma_new,
        )
        rows = []
        for seed, paths in extension["map_paths"].items():
            rows += extra_delta_r(
                config,
                seed,
                [sigma_new],
                paths,
                extension["nosys_spectra"][seed],
                extension["model"],
                extension.get("mask"),
            )
        for row in rows:
            row["delta_r_systematic_only"] = np.nan
        table = pd.concat([table, pd.DataFrame(rows)], ignore_index=True)
        table = table.sort_values(["sigma_g1", "seed"], ignore_index=True)
    return table, regime


def figure8_arguments(output: Mapping, table: pd.DataFrame) -> dict:
    """The arguments of :func:`figures.results.plot_requirement` (Fig. 8) from a run's
    files: ``output`` the requirement stage's requirement.json (a dict), ``table`` its
    delta_r.csv (a DataFrame: sigma_g1, delta_r, delta_r_systematic_only per seed). What
    the stage draws; also what redraws a committed run's figure without its inputs
    (``python -m hwp_tes_systematics figure8``)."""
    missing = {"sigma_g1", "delta_r", "delta_r_systematic_only"} - set(table.columns)
    if missing:
        raise ValueError(f"delta r table: missing columns {sorted(missing)}")
    summary = summarise(table)
    systematic = summarise(
        table.dropna(subset=["delta_r_systematic_only"]).assign(
            delta_r=lambda t: t["delta_r_systematic_only"]
        )
    )
    regime = output["regime"]
    only = output["systematic_only"]
    fraction_point = only["fraction_point"]
    check = output["consistency"]
    failing = ", ".join(f"ell {first}-{last}" for first, last in check["failing_bins"])
    fit = output["power_law_fit"]
    return {
        "sigma": summary["sigma_g1"].to_numpy(),
        "mean": summary["mean_delta_r"].to_numpy(),
        "std": summary["std_delta_r"].to_numpy(),
        "k": regime["k_per_k2"],
        "exponent": fit["exponent"],
        "budget": output["delta_r_budget"],
        "requirement": output["requirement_sigma_g1_per_k"],
        "exponent_sigma": fit["exponent_sigma"],
        "invalid_reason": None if regime["valid"] else regime["reason"],
        "quadratic_threshold": regime["quadratic_threshold_delta_r"],
        "crossing": output["budget_crossing"]["sigma_g1_per_k"],
        "systematic_only": (
            systematic["sigma_g1"].to_numpy(),
            systematic["mean_delta_r"].to_numpy(),
            systematic["std_delta_r"].to_numpy(),
            only["k_per_k2"],
            only["requirement_sigma_g1_per_k"],
        ),
        "fraction_point": (
            fraction_point["sigma_g1_per_k"],
            fraction_point["mean_delta_r"],
            fraction_point["requirement_sigma_g1_per_k"],
        ),
        "inconsistent": None
        if check["consistent"]
        else f"{output['headline']['model']}: fails in {failing}",
    }
