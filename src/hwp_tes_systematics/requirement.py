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

Caveat (see the tests): delta r is exactly quadratic in sigma_g1 only while the
systematic power is a small perturbation, delta r << sigma_r (Fisher width of r). For
larger biases the 68 % point grows faster than the excess power (the cosmic variance of
the tensor modes widens the likelihood), and the fitted exponent exceeds 2.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np
import pandas as pd

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
