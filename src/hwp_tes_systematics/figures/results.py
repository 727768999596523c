"""Result figures: likelihoods of r (cf. Fig. 7 of the study) and the requirement (cf. Fig. 8)."""

from __future__ import annotations

import os
import textwrap
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.ticker import MaxNLocator

from . import save_figure, subplots

X_RANGE_OVER_R68 = 3.0  # the likelihood panel extends to this many times the largest r68


def sigma_label(sigma_g1_per_k: float | None) -> str:
    """Legend label of a sigma_g1 [1/K] value; None or 0: no systematics."""
    if sigma_g1_per_k is None or sigma_g1_per_k == 0:
        return "no systematics"
    return f"sigma_g1 = {sigma_g1_per_k:.0e} K^-1"


def log_axis_yerr(value, std) -> list[np.ndarray]:
    """[lower, upper] error bars of ``value`` +- ``std`` for a log axis: NaN std -> no bar,
    the lower bar clipped so its end stays above 0."""
    value = np.asarray(value, dtype=float)
    std = np.nan_to_num(np.asarray(std, dtype=float), nan=0.0)
    return [np.minimum(std, 0.999 * value), std]


def mark_requirement(axis, requirement: float, budget: float, color: str, name: str) -> None:
    """A dotted vertical line at the requirement and a diamond where it meets the budget;
    its value goes to the legend (``name: sigma_g1 < value``), not into the data area,
    so that no label covers a point, a line or another label."""
    axis.axvline(
        requirement,
        color=color,
        linestyle=":",
        linewidth=1.5,
        label=f"{name}: sigma_g1 < {requirement:.2g} K^-1",
    )
    axis.plot([requirement], [budget], "D", color=color, markersize=6, zorder=5)


def plot_likelihoods(
    r_grid,
    curves: Mapping[str, np.ndarray],
    r68: Mapping[str, float],
    path: str | os.PathLike,
    fraction: float = 0.68,
) -> Path:
    """Normalised likelihoods L(r) (each scaled to a peak of 1) with their 68 % points.

    ``r_grid``: common grid of r; ``curves``: {label: L(r) on r_grid} (e.g. one per
    sigma_g1, labels from :func:`sigma_label`, and "no systematics"); ``r68``: {label: r}
    marked with a dotted vertical line of the curve's colour. x from 0 to
    ``X_RANGE_OVER_R68`` times the largest r68. Writes the PNG atomically; returns its path.
    """
    path = Path(path)
    r_grid = np.asarray(r_grid, dtype=float)
    figure, axis = subplots(figsize=(7.0, 4.5))
    for index, (label, curve) in enumerate(curves.items()):
        curve = np.asarray(curve, dtype=float)
        if curve.shape != r_grid.shape:
            raise ValueError(f"curve {label!r}: shape {curve.shape}, r_grid {r_grid.shape}")
        color = f"C{index % 10}"
        peak = np.max(curve)
        scaled = curve / peak if peak > 0 else curve
        value = r68.get(label)
        text = label if value is None else f"{label} (r{100 * fraction:.0f} = {value:.3g})"
        axis.plot(r_grid, scaled, color=color, label=text)
        if value is not None:
            axis.axvline(value, color=color, linestyle=":", linewidth=1.2)
    finite = [float(v) for v in r68.values() if v is not None and np.isfinite(v) and v > 0]
    x_max = X_RANGE_OVER_R68 * max(finite) if finite else float(r_grid[-1])
    axis.set_xlim(0.0, min(x_max, float(r_grid[-1])))
    axis.set_ylim(0.0, 1.08)
    axis.set_xlabel("tensor-to-scalar ratio r")
    axis.set_ylabel("L(r) / max L")
    axis.set_title(f"Likelihood of r; dotted: {100 * fraction:.0f} % points")
    axis.ticklabel_format(axis="x", style="sci", scilimits=(-3, 3))
    axis.grid(alpha=0.3)
    axis.legend(fontsize="small")
    save_figure(figure, path)
    return path


def plot_requirement(
    sigma,
    mean,
    std,
    k: float,
    exponent: float,
    budget: float,
    requirement: float | None,
    path: str | os.PathLike,
    *,
    exponent_sigma: float | None = None,
    invalid_reason: str | None = None,
    systematic_only: tuple | None = None,
    quadratic_threshold: float | None = None,
    crossing: float | None = None,
    fraction_point: tuple | None = None,
    inconsistent: str | None = None,
) -> Path:
    """Mean delta r over seeds versus sigma_g1 [1/K] (log-log), cf. Fig. 8 of the study.

    Error bars: ``std`` (scatter of delta r across seeds; NaN drawn without bar, and
    clipped so the lower end stays > 0 on the log axis); dashed: the quadratic fit
    k sigma^2 (k in K^2); solid black: the ``budget`` (paper: 6.5e-6,
    ``requirement.DELTA_R_BUDGET``); the requirement sigma (None: sqrt(budget / k))
    marked by a vertical line and a diamond on the budget, its value in the legend
    (:func:`mark_requirement`: no label inside the axes can cover a point); the free
    power-law exponent (and ``exponent_sigma``, if given) in the legend. Points with sigma <= 0 or mean <= 0 are
    not drawn. ``invalid_reason``: the sigma^2 model does not describe the points; the
    reason is written in the legend. ``systematic_only``: (sigma, mean, std, k,
    requirement) of the systematic-only estimator, drawn in a second colour.
    ``quadratic_threshold``: the delta r below which the paper's estimator is quadratic
    (0.1 sigma_r), a dotted grey line. ``crossing``: the sigma at which the points reach
    the budget (:func:`requirement.budget_crossing`), marked instead of the quadratic
    requirement when ``invalid_reason`` is given (and finite). ``fraction_point``:
    (sigma, mean, requirement) of the systematic's own power in the paper's convention
    (the 68 %-point shift), a line. ``inconsistent``: the likelihood model does not
    describe the data (the failing bins, in words), written across the figure.
    Writes the PNG atomically; returns its path.
    """
    path = Path(path)
    sigma = np.asarray(sigma, dtype=float)
    mean = np.asarray(mean, dtype=float)
    std = np.nan_to_num(np.asarray(std, dtype=float), nan=0.0)
    if not sigma.shape == mean.shape == std.shape:
        raise ValueError("sigma, mean and std must have the same shape")
    if requirement is None:
        requirement = float(np.sqrt(budget / k))
    keep = (sigma > 0) & (mean > 0) & np.isfinite(mean)
    sigma, mean, std = sigma[keep], mean[keep], std[keep]

    figure, axis = subplots(figsize=(7.5, 6.4))
    exponent_text = f"{exponent:.3f}"
    if exponent_sigma is not None and np.isfinite(exponent_sigma):
        exponent_text += f" +- {exponent_sigma:.3f}"
    axis.errorbar(
        sigma,
        mean,
        yerr=log_axis_yerr(mean, std),
        fmt="o",
        color="C0",
        capsize=3,
        label=f"mean delta r over seeds (+- std); power-law exponent {exponent_text}",
    )
    show_crossing = invalid_reason is not None and crossing is not None and np.isfinite(crossing)
    span = [crossing if show_crossing else requirement, *sigma]
    if systematic_only is not None:
        span += [systematic_only[4], *systematic_only[0]]
    x = np.logspace(np.log10(np.min(span)) - 0.3, np.log10(np.max(span)) + 0.3, 200)
    label = "paper's estimator: " if systematic_only is not None else ""
    axis.plot(
        x, k * x**2, "--", color="C0", label=f"{label}quadratic fit k sigma^2, k = {k:.3g} K^2"
    )
    if systematic_only is not None:
        sys_sigma, sys_mean, sys_std, sys_k, sys_requirement = systematic_only
        axis.errorbar(
            sys_sigma,
            sys_mean,
            yerr=log_axis_yerr(sys_mean, sys_std),
            fmt="s",
            mfc="none",
            color="C2",
            capsize=3,
            label="systematic only (no-systematics weights, Fisher bias; +- std)",
        )
        axis.plot(x, sys_k * x**2, "-", color="C2", alpha=0.6, label=f"k = {sys_k:.3g} K^2")
        mark_requirement(axis, sys_requirement, budget, "C2", "requirement, Fisher peak shift")
    if fraction_point is not None:
        fp_sigma, fp_mean, fp_requirement = fraction_point
        fp_sigma, fp_mean = np.asarray(fp_sigma), np.asarray(fp_mean)
        shown = (fp_mean > 0) & (fp_sigma >= x[0]) & (fp_sigma <= x[-1])
        axis.plot(
            fp_sigma[shown],
            fp_mean[shown],
            "-",
            color="C1",
            linewidth=2,
            label="systematic only, 68 % point shift (the paper's delta r)",
        )
        if np.isfinite(fp_requirement):
            mark_requirement(axis, fp_requirement, budget, "C1", "requirement, 68 % point")
    axis.axhline(budget, color="k", linestyle="-", label=f"budget delta r = {budget:.2g}")
    if show_crossing:
        mark_requirement(axis, crossing, budget, "C0", "paper's estimator, budget crossing")
    else:
        mark_requirement(axis, requirement, budget, "C3", "paper's estimator, quadratic fit")
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlim(x[0], x[-1])
    axis.set_xlabel("sigma_g1 [K^-1]")
    axis.set_ylabel("mean delta r over seeds" if systematic_only else "mean delta r")
    if quadratic_threshold is not None:
        axis.axhline(
            quadratic_threshold,
            color="gray",
            linestyle=":",
            linewidth=1.0,
            label="0.1 sigma_r: the quadratic regime lies below",
        )
    axis.set_title("Bias on r versus the nonlinearity spread")
    if inconsistent is not None:
        axis.text(
            0.5,
            0.5,
            "INCONSISTENT: the likelihood model does not describe the data\n"
            + textwrap.fill(inconsistent, 60),
            transform=axis.transAxes,
            ha="center",
            va="center",
            fontsize="small",
            color="C3",
            alpha=0.9,
            bbox={"facecolor": "white", "edgecolor": "C3", "alpha": 0.8},
        )
    axis.grid(alpha=0.3, which="both")
    if invalid_reason is not None:
        note = (
            "paper's estimator: sigma^2 does NOT describe the points, "
            + invalid_reason
            + (
                "; marked instead: where the points cross the budget (no model)"
                if show_crossing
                else "; its quadratic requirement (red) is not valid"
            )
        )
        axis.plot([], [], " ", label=textwrap.fill(note, 55))
    # below the axes: inside, it would cover the points
    axis.legend(fontsize="x-small", loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)
    save_figure(figure, path)
    return path


def plot_a2_scaling(by_scale: list[dict], budget: float, path: str | os.PathLike) -> Path:
    """Systematic-only requirement on sigma_g1 versus the HWPSS amplitude scale factor.

    ``by_scale``: [{"a2_scale", "requirement_sigma_g1_per_k",
    "requirement_std_over_seeds_per_k"}, ...]; log-log, with the slopes -1 and -2 through
    a = 1 for reference (the requirement of a pure 2 A_2 s h term scales as 1 / a, of a
    pure A_2^2 h^2 term as 1 / a^2).
    """
    path = Path(path)
    scale = np.array([row["a2_scale"] for row in by_scale], dtype=float)
    value = np.array([row["requirement_sigma_g1_per_k"] for row in by_scale], dtype=float)
    std = np.array([row["requirement_std_over_seeds_per_k"] for row in by_scale], dtype=float)
    order = np.argsort(scale)
    scale, value, std = scale[order], value[order], std[order]
    figure, axis = subplots(figsize=(6.5, 4.5))
    axis.errorbar(
        scale,
        value,
        yerr=log_axis_yerr(value, std),
        fmt="o-",
        color="C2",
        capsize=3,
        label="systematic-only requirement (+- std over seeds)",
    )
    if np.any(scale == 1.0):
        reference = value[scale == 1.0][0]
        axis.plot(
            scale, reference / scale**2, ":", color="gray", label="~ 1 / a^2 (A_2^2 term alone)"
        )
        axis.plot(
            scale, reference / scale, "--", color="gray", label="~ 1 / a (2 A_2 s h term alone)"
        )
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("HWPSS amplitude scale a (A_2 -> a A_2 on every systematics channel)")
    axis.set_ylabel(f"sigma_g1 requirement [K^-1] (delta r = {budget:.2g})")
    axis.set_title("Requirement on sigma_g1 versus the 2f HWPSS amplitude")
    axis.grid(alpha=0.3, which="both")
    axis.legend(fontsize="small")
    save_figure(figure, path)
    return path


def plot_residual_spectra(
    ell,
    residual_bb_by_sigma: Mapping[float, np.ndarray],
    systematic_bb_per_sigma2,
    noise_bb,
    foreground_bb,
    lensing_bb,
    tensor_bb_r1,
    budget: float,
    path: str | os.PathLike,
) -> Path:
    """D_ell^BB = ell (ell + 1) C_ell / 2 pi [uK^2] of the CMB residual, means over seeds.

    ``residual_bb_by_sigma``: {sigma_g1 (0: no systematics): total residual C_ell};
    ``systematic_bb_per_sigma2``: the systematic alone per unit sigma_g1^2 [K^2 K^2],
    drawn dashed at each sigma of the residuals; ``noise_bb``, ``foreground_bb``: the
    no-systematics residual's parts; ``lensing_bb``, ``tensor_bb_r1``: the PTEP spectra,
    the tensor one at r = ``budget`` (the systematic budget) and r = 1e-3.
    """
    path = Path(path)
    ell = np.asarray(ell, dtype=float)
    shown = ell >= 2
    to_dl = ell * (ell + 1) / (2 * np.pi) * 1e12  # K^2 -> uK^2

    def draw(axis, values, *args, **kwargs):
        axis.loglog(ell[shown], (to_dl * np.asarray(values, dtype=float))[shown], *args, **kwargs)

    figure, axis = subplots(figsize=(7.5, 5.0))
    draw(axis, lensing_bb, color="0.3", lw=2, label="lensing BB")
    for r, style in ((1e-3, "-."), (budget, ":")):
        draw(
            axis, r * np.asarray(tensor_bb_r1), color="0.3", ls=style, label=f"tensor BB, r = {r:g}"
        )
    draw(axis, noise_bb, color="tab:gray", lw=1, alpha=0.7, label="noise residual (no sys.)")
    draw(axis, foreground_bb, color="tab:olive", lw=1, alpha=0.7, label="foreground residual")
    colors = iter(("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"))
    for sigma, residual in sorted(residual_bb_by_sigma.items()):
        color = "k" if sigma == 0 else next(colors)
        draw(axis, residual, color=color, lw=1.2, label=f"residual, {sigma_label(sigma)}")
        if sigma > 0:
            draw(axis, sigma**2 * np.asarray(systematic_bb_per_sigma2), color=color, ls="--", lw=1)
    axis.set_xlabel("multipole ell")
    axis.set_ylabel("D_ell^BB [uK^2]")
    axis.set_title("BB of the CMB residual after the HILC (dashed: the systematic alone)")
    axis.legend(fontsize=7, ncol=2)
    save_figure(figure, path)
    return path


def plot_ell_distribution(
    ell,
    information,
    bias,
    model_transfer,
    data_transfer,
    consistency: dict,
    path: str | os.PathLike,
) -> Path:
    """Where in ell sigma_r and the bias come from, and whether the model fits the data.

    Left: the Fisher information F_ell over its sum (:func:`likelihood.fisher_information_per_ell`)
    and the systematic's bias per ell over the total (:func:`likelihood.fisher_bias_per_ell`),
    cumulative. Right: the sky's BB transfer of the model and measured in the data, and
    per bin (``consistency``, :func:`consistency.check_model`) the data's r = 0 BB over
    the model's, failing bins in red.
    """
    path = Path(path)
    ell = np.asarray(ell)
    used = np.asarray(information) > 0
    figure, (left, right) = subplots(1, 2, figsize=(11.0, 4.4))
    info = np.asarray(information)[used] / np.sum(information)
    bias_fraction = np.asarray(bias)[used] / np.sum(bias) if np.sum(bias) != 0 else 0 * info
    left.step(ell[used], np.cumsum(info), where="mid", color="C0", label="1 / sigma_r^2 (Fisher)")
    left.step(
        ell[used], np.cumsum(bias_fraction), where="mid", color="C3", label="bias of the systematic"
    )
    left.set_xscale("log")
    left.set_xlabel("multipole ell")
    left.set_ylabel("cumulative fraction, from lmin")
    left.set_ylim(-0.05, 1.1)
    left.grid(alpha=0.3, which="both")
    left.legend(fontsize="small", loc="lower right")
    left.set_title("Where the information on r and the bias come from")
    right.plot(
        ell[used], np.asarray(model_transfer)[used], color="C0", label="model's sky transfer"
    )
    right.plot(
        ell[used], np.asarray(data_transfer)[used], color="k", lw=1, label="measured T_ell (data)"
    )
    for row in consistency["bins"]:
        first, last = row["ell"]
        ok = row["sky_consistent"] and row["power_consistent"]
        centre = np.sqrt(first * last)
        right.errorbar(
            centre,
            row["data_over_model"],
            yerr=row["data_bb_sem_k2"] / row["model_bb_k2"],
            xerr=[[centre - first], [last - centre]],
            fmt="s",
            color="C2" if ok else "C3",
            capsize=2,
        )
    right.plot([], [], "s", color="C2", label="data / model BB at r = 0, bin consistent")
    right.plot([], [], "s", color="C3", label="... bin fails")
    right.axhline(1.0, color="gray", lw=0.8)
    right.set_xscale("log")
    right.set_xlabel("multipole ell")
    right.set_ylabel("transfer; data / model")
    verdict = "consistent" if consistency["consistent"] else "INCONSISTENT"
    right.set_title(f"Does the model describe the data? {verdict}")
    right.grid(alpha=0.3, which="both")
    right.legend(fontsize="x-small", loc="best")
    save_figure(figure, path)
    return path


def plot_fixed_instruments(
    sigma,
    curves,
    rows: list[dict],
    k_study: float,
    budget: float,
    sigma_r: float,
    path: str | os.PathLike,
) -> Path:
    """Left: ``curves`` (n_instruments, n_sigma), |delta r| = |2 sigma b_i + sigma^2 k_i|
    of each fixed instrument on ``sigma`` [1/K] (grey) and the study's own-power
    k sigma^2 (blue) against the budget; right: each instrument's requirement with its
    linear term and from its own power alone. ``rows``:
    :func:`fixed_instruments.fixed_instrument_estimator`'s ``instruments``."""
    path = Path(path)
    sigma = np.asarray(sigma, dtype=float)
    figure, (left, right) = subplots(1, 2, figsize=(11, 4.5))
    for index, curve in enumerate(curves):
        left.plot(
            sigma, curve, color="0.6", lw=0.8, label="fixed instruments" if index == 0 else None
        )
    left.plot(sigma, k_study * sigma**2, color="C0", lw=2, label="own power, k sigma^2 (study)")
    left.axhline(budget, color="k", ls="--", label=f"budget {budget:.2g}")
    left.axhline(sigma_r, color="C3", ls=":", label=f"sigma_r {sigma_r:.2g}")
    left.set_xscale("log")
    left.set_yscale("log")
    left.set_ylim(budget * 1e-3, max(sigma_r, budget) * 30)
    left.set_xlabel("sigma_g1 [K^-1]")
    left.set_ylabel("|delta r| (Fisher peak shift)")
    left.set_title("Bias of one focal plane (g1 fixed over seeds)")
    left.grid(alpha=0.3, which="both")
    left.legend(fontsize="small", loc="upper left")
    order = np.argsort([row["requirement_sigma_g1_per_k"] for row in rows])
    position = np.arange(len(rows))
    with_linear = np.array([rows[i]["requirement_sigma_g1_per_k"] for i in order])
    quadratic = np.array([rows[i]["requirement_quadratic_only_per_k"] for i in order])
    resolved = np.array([abs(rows[i]["t_linear"]) > 2 for i in order])
    right.plot(position, quadratic, "x", color="C0", label="own power alone")
    right.plot(
        position[~resolved],
        with_linear[~resolved],
        "o",
        mfc="none",
        color="C1",
        label="with linear term (|b| < 2 s.e.)",
    )
    right.plot(
        position[resolved],
        with_linear[resolved],
        "o",
        color="C1",
        label="with linear term (|b| > 2 s.e.)",
    )
    right.set_yscale("log")
    right.xaxis.set_major_locator(MaxNLocator(integer=True))
    right.set_xlabel("instrument (sorted by requirement)")
    right.set_ylabel("requirement on sigma_g1 [K^-1]")
    right.set_title("Requirement per instrument")
    right.grid(alpha=0.3, which="both")
    right.legend(fontsize="small")
    save_figure(figure, path)
    return path
