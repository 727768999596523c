"""The requirement and the information on r against the notch's width, from runs at several D.

    python benchmarks/requirement_vs_notch.py d100/results/requirement.json \\
        d50/results/requirement.json keep_sky/results/requirement.json --figure out.png

Reads each run's ``requirement.json`` (its ``settings.notch_width_divisor`` D, null for no
notch) and prints, per run, ordered from no notch to the widest: delta f / f_HWP = 4 / D,
the random population's requirement on sigma_g1 (the mean over seeds of the 68 %-point
shift, with its bootstrap error; the Fisher peak shift of the systematic's own power),
the paper's estimator where it crosses the budget, sigma_r (the Fisher width of r: what
the filter leaves of the sky's information on r), and whether the likelihood model
describes the data (the model check, the held-out check and r read back on held-out
seeds). With ``--figure``, both requirements and sigma_r against delta f / f_HWP. Where the
runs made the template fit (``mitigation.template_fit``), a second table gives what it buys
at each width: the random population's requirement without and after it (both
conventions), and the requirement on a g1 common to the systematics channels' detectors
(the Fisher one, ``common_offset``) without and after it, with the common offset's
auto term over the random population's after the fit and its linear term's t value.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def reading(path: Path) -> dict:
    """One run's row: its width and the numbers the table prints."""
    data = json.loads(path.read_text())
    headline = data["headline"]
    divisor = data["settings"]["notch_width_divisor"]
    return {
        "path": str(path),
        "divisor": divisor,
        "width_over_f_hwp": 0.0 if divisor is None else 4.0 / divisor,
        "model": headline["model"],
        "requirement_68": headline["requirement_sigma_g1_per_k"],
        "requirement_68_error": headline.get("error_per_k"),
        "requirement_fisher": headline["fisher_peak_shift_requirement_sigma_g1_per_k"],
        "requirement_fisher_error": headline.get("fisher_peak_shift_error_per_k"),
        "paper_estimator": headline.get("paper_estimator_budget_crossing_per_k"),
        "sigma_r": data["sigma_r_fisher"],
        "consistent": headline["consistent"],
        "consistent_held_out": headline.get("consistent_held_out"),
        "r_recovered_consistent": headline.get("r_recovered_consistent"),
        "n_seeds": data["n_seeds"],
        **mitigation_reading(data),
    }


def mitigation_reading(data: dict) -> dict:
    """The template fit's numbers of one run ({} without it)."""
    mitigated = data["systematic_only"].get("mitigated")
    if mitigated is None:
        return {}
    common = data.get("common_offset") or {}
    after = mitigated.get("common_offset") or {}
    return {
        "mitigated_68": mitigated["requirement_sigma_g1_per_k"],
        "mitigated_68_error": mitigated.get("error_per_k"),
        "mitigated_fisher": mitigated["fisher_peak_shift_requirement_sigma_g1_per_k"],
        "common_mu": common.get("requirement_mu_per_k"),
        "common_mu_after_fit": after.get("requirement_mu_per_k"),
        "common_k_over_random_after_fit": after.get("k_over_k_random"),
        "common_t_linear_after_fit": after.get("t_linear"),
    }


def _number(value, error=None) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    if error is None or not math.isfinite(error):
        return f"{value:.3g}"
    return f"{value:.3g} +- {error:.2g}"


def table(rows: list[dict]) -> str:
    lines = [
        (
            "| D | delta f / f_HWP | sigma_g1, 68 % [1/K] | Fisher [1/K] | paper's estimator "
            "[1/K] | sigma_r | model check / held out / r read back | seeds |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        checks = " / ".join(
            {True: "yes", False: "NO", None: "-"}[row[key]]
            for key in ("consistent", "consistent_held_out", "r_recovered_consistent")
        )
        width = "no notch" if row["divisor"] is None else f"{row['divisor']:g}"
        lines.append(
            f"| {width} "
            f"| {row['width_over_f_hwp']:.3f} "
            f"| {_number(row['requirement_68'], row['requirement_68_error'])} "
            f"| {_number(row['requirement_fisher'], row['requirement_fisher_error'])} "
            f"| {_number(row['paper_estimator'])} | {_number(row['sigma_r'])} "
            f"| {checks} | {row['n_seeds']} |"
        )
    return "\n".join(lines)


def mitigation_table(rows: list[dict]) -> str:
    """What the template fit buys at each width (rows with its numbers only; '' if none)."""
    fitted = [row for row in rows if "mitigated_68" in row]
    if not fitted:
        return ""
    lines = [
        "After the template fit (mitigation.template_fit):",
        (
            "| D | random, 68 %: without / after [1/K] | random, Fisher: without / after "
            "[1/K] | common mu, Fisher: without / after [1/K] | after: k_mu / k_sigma, t of b |"
        ),
        "|---|---|---|---|---|",
    ]
    for row in fitted:
        width = "no notch" if row["divisor"] is None else f"{row['divisor']:g}"
        lines.append(
            f"| {width} "
            f"| {_number(row['requirement_68'])} / "
            f"{_number(row['mitigated_68'], row['mitigated_68_error'])} "
            f"| {_number(row['requirement_fisher'])} / {_number(row['mitigated_fisher'])} "
            f"| {_number(row['common_mu'])} / {_number(row['common_mu_after_fit'])} "
            f"| {_number(row['common_k_over_random_after_fit'])}, "
            f"{_number(row['common_t_linear_after_fit'])} |"
        )
    return "\n".join(lines)


def draw(rows: list[dict], path: Path) -> None:
    from hwp_tes_systematics.figures import save_figure, subplots

    x = [row["width_over_f_hwp"] for row in rows]
    fig, (top, bottom) = subplots(2, 1, figsize=(6.0, 6.5), sharex=True)
    for key, error, label, marker in (
        ("requirement_68", "requirement_68_error", "68 % point (paper's convention)", "o"),
        ("requirement_fisher", "requirement_fisher_error", "Fisher peak shift", "s"),
    ):
        top.errorbar(
            x,
            [row[key] for row in rows],
            yerr=[row[error] or 0.0 for row in rows],
            marker=marker,
            capsize=3,
            label=label,
        )
    top.set_yscale("log")
    top.set_ylabel(r"requirement on $\sigma_{g_1}$ [K$^{-1}$]")
    top.legend(fontsize=8)
    bottom.plot(x, [row["sigma_r"] for row in rows], "o-", color="C2")
    bottom.set_yscale("log")
    bottom.set_ylabel(r"$\sigma_r$ (Fisher)")
    bottom.set_xlabel(r"notch width $\delta f / f_{\rm HWP} = 4 / D$ (0: no notch)")
    for row in rows:
        if not (row["consistent"] and row["consistent_held_out"] is not False):
            top.annotate("model check fails", (row["width_over_f_hwp"], row["requirement_68"]))
    save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Example: python benchmarks/requirement_vs_notch.py "
        "d100/results/requirement.json keep_sky/results/requirement.json --figure out.png",
    )
    parser.add_argument("requirements", nargs="+", type=Path, help="requirement.json files")
    parser.add_argument("--figure", type=Path, help="PNG of requirement and sigma_r vs width")
    parser.add_argument("--json", type=Path, help="write the rows as JSON here")
    arguments = parser.parse_args()
    rows = sorted(map(reading, arguments.requirements), key=lambda r: r["width_over_f_hwp"])
    print(table(rows))
    mitigation = mitigation_table(rows)
    if mitigation:
        print("\n" + mitigation)
    if arguments.json:
        arguments.json.write_text(json.dumps(rows, indent=2) + "\n")
    if arguments.figure:
        draw(rows, arguments.figure)
        print(f"figure: {arguments.figure}")


if __name__ == "__main__":
    main()
