"""One table of the requirement from several runs (or readings) of the workflow.

    python benchmarks/compare_runs.py recipe=docs/one_year/paper_recipe \
        transfer=docs/one_year/transfer_in_model literal=docs/one_year/paper_literal

Each argument is NAME=PATH, PATH a ``requirement.json`` or a folder holding one (directly
or in ``results/``). Prints a Markdown table: the likelihood model and whether it
describes the data (``consistency``, with the failing bins), sigma_r, the systematic's
own power in both delta r conventions (the 68 %-point shift, the paper's, and the
Fisher peak shift) with their error (bootstrap over seeds) and the seeds' scatter, the paper's estimator where its mean
crosses the budget, and where the information on r and the bias come from. ``--parts``
adds a second table: the systematic's power k [K^2] through the no-systematics weights
and its two main parts (the fixed template's and the noise term's), the common offset's
requirement from its own power with k_mu / k_sigma, and the fixed instruments' median.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def load(path: Path) -> dict:
    """The requirement.json at ``path`` (a file, or a folder holding it or results/)."""
    for candidate in (path, path / "requirement.json", path / "results" / "requirement.json"):
        if candidate.is_file():
            return json.loads(candidate.read_text())
    raise SystemExit(f"{path}: no requirement.json there, nor in results/")


def fraction(bins: list[dict], key: str, first: int, last: int) -> float:
    """Sum of ``key`` over the bins inside ell first..last."""
    return sum(row[key] for row in bins if row["ell"][0] >= first and row["ell"][1] <= last)


def row(name: str, result: dict) -> str:
    headline = result["headline"]
    settings = result["settings"]
    bins = result["ell_distribution"]["bins"]
    failing = ", ".join(f"{a}-{b}" for a, b in result["consistency"]["failing_bins"]) or "-"
    crossing = result["budget_crossing"]["sigma_g1_per_k"]
    return (
        f"| {name} | {headline['model']} | {settings['notch_width_divisor']} | "
        f"{settings['baseline_length_s']} | {settings['nside']} | "
        f"{'yes' if headline['consistent'] else 'NO'} ({failing}) | "
        f"{headline['sigma_r_fisher']:.3g} | "
        f"**{headline['requirement_sigma_g1_per_k']:.2g}** +- "
        f"{headline.get('error_per_k', float('nan')):.1g} "
        f"(seeds {headline['std_over_seeds_per_k']:.1g}) | "
        f"{headline['fisher_peak_shift_requirement_sigma_g1_per_k']:.2g} +- "
        f"{headline.get('fisher_peak_shift_error_per_k', float('nan')):.1g} "
        f"(seeds {headline['fisher_peak_shift_std_over_seeds_per_k']:.1g}) | {crossing:.2g} | "
        f"{fraction(bins, 'information_fraction', 2, 4):.2f} | "
        f"{fraction(bins, 'bias_fraction', 21, 80):.2f} |"
    )


def parts_row(name: str, result: dict) -> str:
    """k and its parts, the common offset, the fixed instruments (``--parts``)."""
    own = result["systematic_only"]
    split = own["template_split"]["k_per_k2"]
    common = result["common_offset"]
    return (
        f"| {name} | {own['k_per_k2']:.3g} | {split['fixed_x_fixed']:.3g} | "
        f"{split['noise_h_x_noise_h']:.3g} | "
        f"{common['requirement_mu_quadratic_only_per_k']:.2g} | {common['k_over_k_random']:.2g} | "
        f"{result['fixed_instruments']['requirement_median_per_k']:.2g} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="NAME=PATH")
    parser.add_argument("--parts", action="store_true", help="the table of k's parts too")
    arguments = parser.parse_args()
    named = [item.partition("=") for item in arguments.runs]
    results = [(name, load(Path(path))) for name, _, path in named]
    print(
        "| reading | likelihood model | notch divisor | baselines [s] | nside | "
        "model describes the data (failing ell bins) | sigma_r | sigma_g1 < [1/K], 68 % "
        "point (paper's convention) | sigma_g1 < [1/K], Fisher peak shift | paper's "
        "estimator, budget crossing [1/K] | information from ell 2-4 | bias from ell 21-80 |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, result in results:
        print(row(name, result))
    if arguments.parts:
        print(
            "\n| reading | k [K^2] | fixed x fixed | noise term x noise term | common offset: mu_g1 bound "
            "[1/K], own power | k_mu / k_sigma | fixed instruments, median [1/K] |"
        )
        print("|---|---|---|---|---|---|---|")
        for name, result in results:
            print(parts_row(name, result))


if __name__ == "__main__":
    main()
