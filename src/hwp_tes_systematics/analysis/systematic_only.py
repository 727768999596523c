"""The requirement from the systematic's own power, per seed, and what mitigation buys.

k_seed = delta r_Fisher / sigma_g1^2 is the Fisher bias of the systematic through the
no-systematics HILC weights (:mod:`.ilc_residuals`), exactly quadratic in sigma_g1: its
mean over seeds gives sigma_req = sqrt(budget / k) with a bootstrap error over the seeds
(:func:`systematic_only_estimator`); the shift of the 68 % point that the systematic's
own power makes, the paper's reading on that power (:func:`fraction_point_estimator`);
the same after the map-based template fit (:func:`mitigation_summary`); and the share of
each part of the template (:func:`template_split`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .channel_alms import TEMPLATE_PARTS
from .likelihood import fisher_bias
from .requirement import budget_crossing, crossing_outside_grid, requirement_sigma

BOOTSTRAP_RESAMPLES = 2000  # resamplings of the seeds for the error of a requirement
BOOTSTRAP_SEED = 26  # fixed: the error is reproducible bit for bit


def bootstrap_error(per_seed: np.ndarray, statistic) -> float:
    """Standard deviation over BOOTSTRAP_RESAMPLES resamplings (with replacement) of the
    rows of ``per_seed`` (one per seed) of ``statistic(rows)``: the statistical error of
    a requirement computed from the mean over seeds (not the seeds' scatter)."""
    per_seed = np.asarray(per_seed, dtype=float)
    if len(per_seed) < 2:
        return float("nan")
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    draws = rng.integers(0, len(per_seed), size=(BOOTSTRAP_RESAMPLES, len(per_seed)))
    values = np.array([statistic(per_seed[rows]) for rows in draws])
    return float(np.nanstd(values, ddof=1))


def fraction_point_estimator(
    likelihoods: list[dict], budget: float, block=lambda r: r["systematic_only"]
) -> dict:
    """The systematic-only requirement in the paper's convention: the sigma_g1 at which
    the mean over seeds of the 68 %-point shift (rule likelihood,
    ``fraction_point_shift`` of ``block(likelihood)``) reaches the budget
    (:func:`budget_crossing`, log-log between grid points), each seed's own crossing, and
    the local exponent at the two smallest sigma_g1 (2 if the shift is quadratic there:
    a check, not an assumption)."""
    shifts = [block(r)["fraction_point_shift"] for r in likelihoods]
    sigma = np.array(shifts[0]["sigma_g1_per_k"])
    per_seed = np.array([s["delta_r"] for s in shifts], dtype=float)  # NaN: not computed
    mean = per_seed.mean(axis=0)  # NaN where any seed stopped: skipped by budget_crossing
    crossing = budget_crossing(sigma, mean, budget)
    seeds = [budget_crossing(sigma, row, budget) for row in per_seed]
    finite = [value for value in seeds if np.isfinite(value)]
    small = np.log(mean[1] / mean[0]) / np.log(sigma[1] / sigma[0]) if mean[0] > 0 else np.nan
    return {
        "definition": "sigma_g1 where the mean over seeds of r_68(C_nosys + sigma^2 C_sys) - "
        "r_68(C_nosys) reaches the budget (the paper's delta r, the shift of the 68 % point, "
        "for the systematic's own power)",
        "requirement_sigma_g1_per_k": crossing,
        "outside_grid": crossing_outside_grid(sigma, mean, budget),
        "requirement_per_seed_per_k": seeds,
        "requirement_std_over_seeds_per_k": float(np.std(finite, ddof=1))
        if len(finite) > 1
        else float("nan"),
        "requirement_error_per_k": bootstrap_error(
            per_seed, lambda rows: budget_crossing(sigma, rows.mean(axis=0), budget)
        ),
        "sigma_g1_per_k": sigma.tolist(),
        "mean_delta_r": mean.tolist(),
        "std_delta_r": np.nan_to_num(per_seed.std(axis=0, ddof=1), nan=0.0).tolist()
        if len(per_seed) > 1
        else [float("nan")] * sigma.size,
        "exponent_at_smallest_sigma": float(small),
    }


def systematic_only_estimator(likelihoods: list[dict], budget: float, sigma_r: float) -> dict:
    """Requirement from delta r = k sigma^2 with k the mean over seeds of the Fisher bias;
    its scatter over seeds; and the same for each HWPSS scale factor."""
    k_seeds = np.array([r["systematic_only"]["k_per_k2"] for r in likelihoods])
    k_mean = float(k_seeds.mean())
    per_seed = [requirement_sigma(k, budget) for k in k_seeds if k > 0]
    by_scale = []
    scales = [row["a2_scale"] for row in likelihoods[0]["systematic_only"]["k_per_k2_by_a2_scale"]]
    for index, scale in enumerate(scales):
        k_scale = np.array(
            [r["systematic_only"]["k_per_k2_by_a2_scale"][index]["k_per_k2"] for r in likelihoods]
        )
        by_scale.append(
            {
                "a2_scale": scale,
                "k_per_k2": float(k_scale.mean()),
                "requirement_sigma_g1_per_k": requirement_sigma(float(k_scale.mean()), budget),
                "requirement_std_over_seeds_per_k": float(
                    np.std([requirement_sigma(k, budget) for k in k_scale], ddof=1)
                )
                if len(k_scale) > 1
                else float("nan"),
            }
        )
    valid = bool(k_mean > 0 and budget < 0.1 * sigma_r)
    return {
        "definition": "delta r = k sigma_g1^2, k = Fisher bias of the BB spectrum of the "
        "systematic alone through the no-systematics HILC weights (the shift of the "
        "likelihood's peak; signed, exactly quadratic)",
        "k_per_k2": k_mean,
        "k_per_seed": k_seeds.tolist(),
        "requirement_sigma_g1_per_k": requirement_sigma(k_mean, budget),
        "requirement_error_per_k": bootstrap_error(
            k_seeds, lambda rows: requirement_sigma(rows.mean(), budget)
        )
        if k_mean > 0
        else float("nan"),
        "requirement_per_seed_per_k": per_seed,
        "requirement_std_over_seeds_per_k": float(np.std(per_seed, ddof=1))
        if len(per_seed) > 1
        else float("nan"),
        "valid": valid,
        "reason": "exactly quadratic; the budget is in the linear (Fisher) regime, "
        f"budget / sigma_r = {budget / sigma_r:.2g}"
        if valid
        else "the budget is not small next to sigma_r: the linear bias does not apply",
        "by_a2_scale": by_scale,
    }


def mitigation_summary(likelihoods: list[dict], budget: float, template_fits: list[dict]) -> dict:
    """The requirement after the template fit in both conventions (the 68 %-point shift,
    :func:`fraction_point_estimator`; the Fisher peak shift k_mit sigma^2, k_mit the mean
    over seeds), the fit's own cost on r (mean and standard error over seeds), and per
    systematics channel the g1 it recovers (``template_fits``: the seeds' reports of
    :meth:`channel_alms.ChannelAlms.template_fit`): the slope of the fitted response on
    the injected draws, sum(response x draw) / sum(draw^2) (1: unbiased), the rms of the
    fit's error over seeds and detectors, and of its formal error."""
    mitigated = [r["systematic_only"]["mitigated"] for r in likelihoods]
    k_seeds = np.array([m["k_per_k2"] for m in mitigated])
    cost = np.array([m["fit_cost_delta_r"] for m in mitigated])
    fraction_point = fraction_point_estimator(
        likelihoods, budget, lambda r: r["systematic_only"]["mitigated"]
    )
    channels = {}
    for report in (c for fit in template_fits for c in fit["channels"]):
        entry = channels.setdefault(
            report["channel"], {"response": [], "error": [], "formal": [], "rank": []}
        )
        injected = np.asarray(report["injected_unit_draw"], dtype=float)
        response = np.asarray(report["fitted_unit_response"], dtype=float)
        entry["response"].append(float(response @ injected / (injected @ injected)))
        entry["error"].extend(report["fit_error_per_k"])
        entry["formal"].extend(report["formal_error_per_k"])
        entry["rank"].append(report["rank"])
    per_channel = {
        name: {
            "fitted_over_injected": float(np.mean(e["response"])),
            "fitted_over_injected_std": float(np.std(e["response"], ddof=1))
            if len(e["response"]) > 1
            else float("nan"),
            "g1_error_rms_per_k": float(np.sqrt(np.mean(np.square(e["error"])))),
            "g1_formal_error_rms_per_k": float(np.sqrt(np.mean(np.square(e["formal"])))),
            "rank": int(min(e["rank"])),
        }
        for name, e in channels.items()
    }
    k_mean = float(k_seeds.mean())
    return {
        "definition": "the systematic-only requirement after map-based template fitting "
        "(analysis.template_fit): what the fit leaves of the systematic, on the residual "
        "that has lost the sky along the templates",
        "basis": mitigated[0]["basis"],
        "templates_known": sorted(
            {c["templates_known"] for f in template_fits for c in f["channels"]}
        ),
        "requirement_sigma_g1_per_k": fraction_point["requirement_sigma_g1_per_k"],
        "error_per_k": fraction_point["requirement_error_per_k"],
        "fraction_point": fraction_point,
        "fisher_peak_shift_requirement_sigma_g1_per_k": requirement_sigma(k_mean, budget)
        if k_mean > 0
        else float("inf"),
        "k_per_k2": k_mean,
        "k_per_seed": k_seeds.tolist(),
        "fit_cost_delta_r": float(cost.mean()),
        "fit_cost_delta_r_sem": float(cost.std(ddof=1) / np.sqrt(cost.size))
        if cost.size > 1
        else float("nan"),
        "fit_cost_over_budget": float(cost.mean() / budget),
        "per_channel": per_channel,
    }


def template_split(tables: list[pd.DataFrame], model, budget: float) -> dict | None:
    """Where the systematic's own power comes from (map-domain path): the Fisher bias k
    [K^2] of the seeds' mean BB of each pair of the template's parts (fixed: the
    seed-independent sky through the nonlinearity; cmb_h, noise_h: the seed's CMB and noise
    through the s h term), the share of each, and the requirement without the noise x h
    part (what cross-spectra of data splits, whose noise is independent, would leave);
    from the seeds' systematic spectra ``tables``."""
    size = model.ell.size
    pairs = [(a, b) for i, a in enumerate(TEMPLATE_PARTS) for b in TEMPLATE_PARTS[i:]]
    if not tables or f"bb_{pairs[0][0]}_x_{pairs[0][1]}_k4" not in tables[0]:
        return None
    k = {}
    for a, b in pairs:
        mean = np.mean([t[f"bb_{a}_x_{b}_k4"].to_numpy()[:size] for t in tables], axis=0)
        k[f"{a}_x_{b}"] = (1 if a == b else 2) * fisher_bias(mean, model)
    total = sum(k.values())
    without_noise = sum(value for pair, value in k.items() if "noise_h" not in pair)
    return {
        "definition": "k [K^2] of each pair of the template's parts (crosses counted "
        "twice), from the seeds' mean BB through the no-systematics weights; they sum to k",
        "k_per_k2": k,
        "fraction_of_k": {pair: value / total for pair, value in k.items()},
        "k_without_noise_h_per_k2": without_noise,
        "requirement_without_noise_h_per_k": requirement_sigma(without_noise, budget)
        if without_noise > 0
        else float("nan"),
    }
