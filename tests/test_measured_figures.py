"""The README's requirement figures are the committed runs' numbers.

Each row of the README's table of readings names the run files it quotes (the mapping
below); every figure of the row (sigma_r, the 68 %-point requirement and its error, the
Fisher peak shift) must be the run's ``requirement.json`` value rounded to the digits
quoted, and the range the README draws from them must be their minimum and maximum.
A page that drifts from its files fails here.
"""

import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ONE_YEAR = "docs/one_year"
RESOLUTION = "docs/resolution"
ROWS = {  # README row label (start) -> the requirement.json files it quotes, in order
    "**the answer**": [f"{ONE_YEAR}/requirement.json"],
    "a filter that keeps the sky": [f"{ONE_YEAR}/readings/keep_sky/requirement.json"],
    "without ell 2-4": [f"{ONE_YEAR}/readings/lmin5/requirement.json"],
    "nside 128 / 256 / 512": [
        f"{RESOLUTION}/nside{n}_baselines60s/requirement.json" for n in (128, 256, 512)
    ],
    "one offset per detector per day": [f"{RESOLUTION}/nside64_baselines86400s/requirement.json"],
    "no offset removed (": [f"{RESOLUTION}/nside64_nobaselines/requirement.json"],
    "no offset removed, nside 128": [
        f"{RESOLUTION}/nside{n}_nobaselines/requirement.json" for n in (128, 256, 512)
    ],
}
OFFSETS_REMOVED = ROWS.keys() - {"no offset removed (", "no offset removed, nside 128"}
NUMBER = r"(\d+(?:\.\d+)?)e(-?\d+)"


def readme_rows() -> dict[str, list[str]]:
    rows = {}
    for line in (REPO / "README.md").read_text().splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        for label in ROWS:
            if line.startswith("| ") and cells[0].startswith(label):
                rows[label] = cells[1:]
    return rows


def quoted(cell: str) -> list[tuple[float, int, int]]:
    """(value, exponent, mantissa decimals) of each number of a cell, in order."""
    return [
        (float(f"{m}e{e}"), int(e), len(m.split(".")[1]) if "." in m else 0)
        for m, e in re.findall(NUMBER, cell.replace("*", ""))
    ]


def matches(value: float, quote: tuple[float, int, int]) -> bool:
    """``value`` rounded to the quote's digits (its exponent, its decimals) is the quote."""
    number, exponent, decimals = quote
    return round(value / 10.0**exponent, decimals) == round(number / 10.0**exponent, decimals)


def run_values(path: str) -> dict[str, float]:
    result = json.loads((REPO / path).read_text())
    headline = result["headline"]
    return {
        "sigma_r": result["sigma_r_fisher"],
        "requirement": headline["requirement_sigma_g1_per_k"],
        "error": headline["error_per_k"],
        "fisher": headline["fisher_peak_shift_requirement_sigma_g1_per_k"],
        "std_over_seeds": headline["std_over_seeds_per_k"],
        "consistent": headline["consistent"],
    }


@pytest.mark.parametrize("label", list(ROWS))
def test_each_reading_of_the_readme_is_its_runs_requirement_json(label):
    rows = readme_rows()
    assert label in rows, f"README: no row of the readings table starts with {label!r}"
    sigma_r_cell, requirement_cell, fisher_cell = rows[label]
    runs = [run_values(path) for path in ROWS[label]]
    assert all(run["consistent"] for run in runs), f"{label}: a run quoted is not consistent"
    n = len(runs)
    requirements = quoted(requirement_cell)
    for key, quotes in (
        ("sigma_r", quoted(sigma_r_cell)),
        ("requirement", requirements[:n]),
        ("fisher", quoted(fisher_cell)),
    ):
        assert len(quotes) == n, f"{label}: {key} quotes {quotes} for {n} runs"
        for run, quote, path in zip(runs, quotes, ROWS[label], strict=True):
            assert matches(run[key], quote), (
                f"{label}: {key} {quote[0]:g} but {path} has {run[key]:.4g}"
            )
    if n == 1:  # "x +- e": the bootstrap error of the seeds' mean
        assert matches(runs[0]["error"], requirements[1]), (
            f"{label}: error {requirements[1][0]:g}, {ROWS[label][0]} has {runs[0]['error']:.3g}"
        )
    else:  # "(+- a-b e-x)": every run's error within the quoted range, to its digits
        found = re.search(r"\(\+- (\d+\.\d+)-(\d+\.\d+)e(-?\d+)\)", requirement_cell)
        assert found, f"{label}: no error range in {requirement_cell!r}"
        low, high, exponent = float(found[1]), float(found[2]), int(found[3])
        for run, path in zip(runs, ROWS[label], strict=True):
            error = round(run["error"] / 10.0**exponent, 1)
            assert low <= error <= high, f"{label}: {path} error {run['error']:.3g} outside"


def test_the_answer_and_the_range_of_readings_are_the_runs():
    text = (REPO / "README.md").read_text()
    answer = run_values(ROWS["**the answer**"][0])
    found = re.search(
        rf"\*\*sigma_g1 < {NUMBER} \+- {NUMBER} K\^-1\*\* \(the seeds scatter by {NUMBER}\)", text
    )
    assert found, "README: the answer's sentence is not where it was"
    values = [
        (
            float(f"{found[i]}e{found[i + 1]}"),
            int(found[i + 1]),
            len(found[i].split(".")[1]) if "." in found[i] else 0,
        )
        for i in (1, 3, 5)
    ]
    for key, quote in zip(("requirement", "error", "std_over_seeds"), values, strict=True):
        assert matches(answer[key], quote), f"the answer's {key}: {quote[0]:g} vs {answer[key]:.3g}"
    fisher = re.search(rf"Fisher peak shift: {NUMBER}\.", text)
    assert matches(answer["fisher"], quoted(fisher[0])[0])
    spread = re.search(rf"\*\*{NUMBER} to {NUMBER} K\^-1\*\* \({NUMBER} to {NUMBER} Fisher\)", text)
    assert spread, "README: the range of readings with offsets removed is not where it was"
    runs = [run_values(path) for label in OFFSETS_REMOVED for path in ROWS[label]]
    bounds = quoted(spread[0])
    assert matches(min(r["requirement"] for r in runs), bounds[0])
    assert matches(max(r["requirement"] for r in runs), bounds[1])
    assert matches(min(r["fisher"] for r in runs), bounds[2])
    assert matches(max(r["fisher"] for r in runs), bounds[3])
