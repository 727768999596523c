"""One table of the requirement from several runs of the workflow (e.g. the default and
its variants: paper-literal path without baselines, g1 per pair, notch transfer in
the model).

    python benchmarks/compare_runs.py default=/tmp/runs/default literal=/tmp/runs/literal

Each argument is NAME=FOLDER, FOLDER holding the run's ``results/requirement.json``.
Prints a Markdown table: the settings that differ, both estimators' requirement on
sigma_g1 (with the scatter over seeds for the systematic-only one), the paper
estimator's free exponent, its validity, and the systematic-only requirement at the
A_2 scale 0.5 (the projection convention).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def row(name: str, folder: Path) -> str:
    result = json.loads((folder / "results" / "requirement.json").read_text())
    settings = result["settings"]
    systematic = result["systematic_only"]
    by_scale = {entry["a2_scale"]: entry for entry in systematic["by_a2_scale"]}
    half = by_scale.get(0.5, {}).get("requirement_sigma_g1_per_k", float("nan"))
    regime = result["regime"]
    points = ", ".join(
        f"{p['sigma_g1_per_k']:.0e}: {p['mean_delta_r']:.2g}"
        for p in result["per_sigma"] + result["extended_per_sigma"]
    )
    return (
        f"| {name} | {settings['baseline_length_s']} | {settings['g1_per']} | "
        f"{settings.get('likelihood_model', settings.get('notch_transfer_in_model'))} | {result['requirement_sigma_g1_per_k']:.2g} | "
        f"{result['power_law_fit']['exponent']:.2f} +- "
        f"{result['power_law_fit']['exponent_sigma']:.2f} | {regime['valid']} | "
        f"{systematic['requirement_sigma_g1_per_k']:.2g} +- "
        f"{systematic['requirement_std_over_seeds_per_k']:.1g} | {half:.2g} | "
        f"{result['sigma_r_fisher']:.2g} | {points} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="NAME=FOLDER")
    arguments = parser.parse_args()
    print(
        "| run | baselines [s] | g1 per | T_ell in model | paper's requirement [1/K] | "
        "paper's free exponent | sigma^2 valid | systematic-only requirement [1/K] | "
        "systematic-only, A_2 x 0.5 | sigma_r | paper's mean delta r per sigma |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for item in arguments.runs:
        name, _, folder = item.partition("=")
        print(row(name, Path(folder)))


if __name__ == "__main__":
    main()
