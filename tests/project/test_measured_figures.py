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

REPO = Path(__file__).resolve().parents[2]
ONE_YEAR = "docs/one_year"
RESOLUTION = "docs/resolution"
ROWS = {  # README row label (start) -> the requirement.json files it quotes, in order
    "**the answer**": [f"{ONE_YEAR}/recovered_power/requirement.json"],
    "the first one-year run": [f"{ONE_YEAR}/requirement.json"],
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
# the first run's readings (one likelihood model) that remove offsets: the README's range
OFFSETS_REMOVED = ROWS.keys() - {
    "**the answer**",
    "no offset removed (",
    "no offset removed, nside 128",
}
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
    text = " ".join((REPO / "README.md").read_text().split())  # as read, whatever the wrapping
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


# Whole-run costs: each has one source, a run record, and the pages quote it or link to it.
DEFAULT_RUN = REPO / "docs" / "default_run" / "run.json"
ONE_DAY_RUN = REPO / "docs" / "one_day" / "run.json"
ONE_YEAR_RUN = REPO / "docs" / "one_year" / "recovered_power" / "run.json"
# jobs of a configuration's DAG (a dry run checks each: test_job_counts_are_the_dags)
JOB_COUNTS = {
    "config/config.yaml": 197,
    "config/one_day.yaml": 70,
    "config/one_year.yaml": 197,
    "config/one_day.yaml tests/configs/tiny.yaml": 26,
    "config/one_year.yaml config/paper.yaml config/full_focal_plane.yaml": 757,
}
PAGES = [REPO / "README.md"] + sorted(
    p for p in (REPO / "docs").rglob("*.md") if not {"_build", "_generated"} & set(p.parts)
)


def minutes(text: str) -> float:
    """'1 h 58 min', '4 min 11 s', '255 s' -> minutes."""
    units = {"h": 60.0, "min": 1.0, "s": 1 / 60}
    found = re.findall(r"(\d+(?:\.\d+)?) (h|min|s)\b", text)
    assert found, text
    return sum(float(value) * units[unit] for value, unit in found)


def test_the_run_records_hold_their_configurations_job_counts():
    default, year = (json.loads(p.read_text()) for p in (DEFAULT_RUN, ONE_YEAR_RUN))
    assert default["command"] == "snakemake --cores 2"
    assert default["jobs"] == JOB_COUNTS["config/config.yaml"]
    assert year["command"] == "snakemake --cores 2 --configfile config/one_year.yaml"
    assert year["jobs"] == JOB_COUNTS["config/one_year.yaml"]
    one_day = json.loads(ONE_DAY_RUN.read_text())
    assert one_day["jobs"] == JOB_COUNTS["config/one_day.yaml"]


def test_the_readme_quotes_the_run_records():
    """The README's run times and job counts are the records' (rounded as quoted)."""
    readme = (REPO / "README.md").read_text()
    default = json.loads(DEFAULT_RUN.read_text())
    jobs, quoted_min = re.search(r"\((\d+) jobs in about (\d+) minutes on 2 cores", readme).groups()
    assert int(jobs) == default["jobs"]
    assert int(quoted_min) == round(default["wall_s"] / 60)
    year = json.loads(ONE_YEAR_RUN.read_text())
    jobs, hours = re.search(
        r"config/one_year\.yaml` \((\d+) jobs, about (\d+) h here\)", readme
    ).groups()
    assert int(jobs) == year["jobs"]
    assert int(hours) == round(year["wall_s"] / 3600)


def test_the_readme_quotes_the_default_runs_answer():
    """The README's default answer, its error and its ratio to the year are the committed
    default run's requirement.json (docs/default_run/)."""
    readme = " ".join((REPO / "README.md").read_text().split())
    found = re.search(
        rf"\*\*sigma_g1 < {NUMBER} \+- {NUMBER} K\^-1\*\*, consistent, (\d+\.\d+) times tighter "
        "than the year's",
        readme[readme.index("**The default**") :],
    )
    assert found, "README: the default's answer is not where it was"
    result = json.loads((REPO / "docs/default_run/requirement.json").read_text())
    headline = result["headline"]
    assert headline["consistent"] and headline["consistent_held_out"]
    value, error = quoted(found[0])[:2]
    assert matches(headline["requirement_sigma_g1_per_k"], value)
    assert matches(headline["error_per_k"], error)
    ratio = headline["one_year_answer"]["one_year_over_this_run"]
    assert f"{ratio:.2f}" == found[5]


def test_the_configuration_table_quotes_the_run_records():
    table = (REPO / "docs" / "workflow" / "configuration.md").read_text()
    for record, row_start in (
        (DEFAULT_RUN, "| `config/config.yaml`"),
        (ONE_DAY_RUN, "| `config/one_day.yaml`"),
        (ONE_YEAR_RUN, "| `config/one_year.yaml`"),
    ):
        run = json.loads(record.read_text())
        (row,) = [line for line in table.splitlines() if line.startswith(row_start)]
        cost = row.split("|")[3]
        assert f"{run['jobs']} jobs in " in cost, row
        assert record.relative_to(REPO).as_posix() in cost, row
        quoted = minutes(cost.split(" jobs in ")[1].split(" on ")[0])
        assert abs(quoted - run["wall_s"] / 60) < 0.5, (row, run["wall_s"])


def test_every_job_count_on_a_page_is_a_configurations():
    """'N jobs' on any page is the DAG of a configuration (JOB_COUNTS) or of the tiny test
    configuration, unless given as an estimate ('~N', 'about N'): a count from an older
    DAG fails here."""
    allowed = set(JOB_COUNTS.values())
    stale = [
        f"{page.relative_to(REPO)}:{text[: match.start()].count(chr(10)) + 1}: {match.group(0)}"
        for page in PAGES
        for text in [page.read_text()]
        for match in re.finditer(r"(~|about )?\b(\d[\d,]*) jobs\b", text)
        if not match.group(1) and int(match.group(2).replace(",", "")) not in allowed
    ]
    assert not stale, "\n".join(stale)


def test_no_page_quotes_a_test_count():
    """Test counts change with every test added: pages give the tiers' wall time instead."""
    counts = [
        f"{page.relative_to(REPO)}: {match.group(0)}"
        for page in PAGES
        for match in re.finditer(r"\b\d+ (tests (in|passed)|passed in)\b", page.read_text())
    ]
    assert not counts, "\n".join(counts)


@pytest.mark.slow
@pytest.mark.parametrize("configfile", JOB_COUNTS)
def test_job_counts_are_the_dags(configfile, tmp_path):
    """A dry run of each configuration (its files merged in order) schedules
    JOB_COUNTS[configfile] jobs (the default's with no --configfile: the embedded
    configuration)."""
    from helpers import make_workdir, snakemake

    workdir = make_workdir(REPO, tmp_path / "workdir")
    files = [str(REPO / name) for name in configfile.split()]
    extra = ("-n",) if configfile == "config/config.yaml" else ("-n", "--configfile", *files)
    result = snakemake(workdir, extra=extra)
    assert result.returncode == 0, result.stderr[-3000:]
    total = re.search(r"^total\s+(\d+)$", result.stdout + result.stderr, re.MULTILINE)
    assert total and int(total.group(1)) == JOB_COUNTS[configfile], (result.stdout + result.stderr)[
        -3000:
    ]


def beside_the_paper_rows() -> list[tuple[str, list[str], list[str]]]:
    """(label, requirement.json paths, [sigma_r, 68 % point, Fisher, crossing] cells) of
    each row of docs/results/one_year.md's table of readings that names its run folders
    (``.../`` is docs/resolution/, ``{a,b}`` one folder each)."""
    rows = []
    for line in (REPO / "docs/results/one_year.md").read_text().splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 7 or not cells[2].startswith("`") or "docs" not in cells[2] + "...":
            continue
        folder = cells[2].strip("`").replace(".../", "docs/resolution/")
        braces = re.search(r"\{([^}]+)\}", folder)
        folders = (
            [folder.replace(braces[0], part) for part in braces[1].split(",")]
            if braces
            else [folder]
        )
        paths = [f"{f}/requirement.json" for f in folders]
        if all((REPO / path).is_file() for path in paths):
            rows.append((cells[0], paths, cells[3:7]))
    return rows


def test_the_results_page_readings_are_their_runs_requirement_json():
    """docs/results/one_year.md's readings beside the paper quote each run folder's
    requirement.json (sigma_r, the 68 %-point requirement, the Fisher peak shift and the
    paper's estimator's budget crossing), rounded as quoted."""
    rows = beside_the_paper_rows()
    assert len(rows) >= 10, rows
    for label, paths, cells in rows:
        runs = [json.loads((REPO / path).read_text()) for path in paths]
        values = {
            "sigma_r": [run["sigma_r_fisher"] for run in runs],
            "68 % point": [run["headline"]["requirement_sigma_g1_per_k"] for run in runs],
            "Fisher": [
                run["headline"]["fisher_peak_shift_requirement_sigma_g1_per_k"] for run in runs
            ],
            "crossing": [run["headline"]["paper_estimator_budget_crossing_per_k"] for run in runs],
        }
        for (key, expected), cell in zip(values.items(), cells, strict=True):
            if cell.startswith("<"):  # a bound, not a value
                continue
            quotes = [q for q in quoted(cell) if q[0] > 0]
            numbers = quotes if len(paths) == 1 else quotes[: len(paths)]
            if len(paths) > 1 and "+-" in cell:  # "a +- e / b +- e": every other number
                numbers = quotes[0::2][: len(paths)]
            for value, quote in zip(expected, numbers[: len(expected)], strict=False):
                assert matches(value, quote), f"{label}: {key} {quote[0]:g}, run has {value:.4g}"


def test_the_readme_quotes_the_emulated_focal_planes_answer():
    """The README's focal-plane answer (random sigma_g1, its error, the Fisher reading, the
    common |mu_g1| from its own power and with its linear term, the paper's estimator) is
    the committed emulation of every pair from the year at two pairs in the field-of-view
    layout (docs/focal_plane/emulated/ey2all/), a run whose checks pass; the readings from
    one pair beside it are ey1fovall/ (field of view) and ey1all/ (boresight)."""
    readme = " ".join((REPO / "README.md").read_text().split())
    found = re.search(
        rf"\*\*For LiteBIRD's focal plane: sigma_g1 < {NUMBER} \+- {NUMBER} K\^-1\*\* for a g1 "
        rf"drawn per detector \(the 68 %-point shift for the systematic's own power, averaged "
        rf"over g1 draws; Fisher {NUMBER}\) and \*\*\|mu_g1\| < {NUMBER} K\^-1\*\* for one common to "
        rf"every detector \(Fisher, own power; {NUMBER} with its linear term\)",
        readme,
    )
    assert found, "README: the focal plane's answer is not where it was"
    emulated = REPO / "docs/focal_plane/emulated"
    result = json.loads((emulated / "ey2all/requirement.json").read_text())
    headline = result["headline"]
    assert headline["consistent"] and headline["consistent_held_out"]
    assert headline["r_recovered_consistent"]
    settings = result["settings"]
    assert settings["emulated_pairs_per_channel"] == "all"
    assert (settings["pairs_per_channel"], settings["detector_positions"]) == (2, "field_of_view")
    values = quoted(found[0])
    expected = (
        headline["requirement_sigma_g1_per_k"],
        headline["error_per_k"],
        headline["fisher_peak_shift_requirement_sigma_g1_per_k"],
        result["common_offset"]["requirement_mu_quadratic_only_per_k"],
        result["common_offset"]["requirement_mu_per_k"],
    )
    for value, quote in zip(expected, values, strict=True):
        assert matches(value, quote), f"{quote[0]:g} vs {value:.3g}"
    beside = re.search(
        rf"from one pair it reads {NUMBER} in that layout, {NUMBER} with every detector on the "
        rf"boresight",
        readme,
    )
    crossing = re.search(rf"The paper's estimator crosses at {NUMBER}\.", readme)
    assert beside and crossing, "README: the readings beside the answer are not where they were"
    expected = [
        json.loads((emulated / f"{name}/requirement.json").read_text())["headline"][
            "requirement_sigma_g1_per_k"
        ]
        for name in ("ey1fovall", "ey1all")
    ] + [headline["paper_estimator_budget_crossing_per_k"]]
    quotes = quoted(beside[0]) + quoted(crossing[0])
    for value, quote in zip(expected, quotes, strict=True):
        assert matches(value, quote), f"{quote[0]:g} vs {value:.3g}"


def test_the_readme_quotes_the_year_at_two_pairs():
    """The README's run of the year at two pairs per channel (its 68 % point and error),
    against which the emulation from one pair is measured, is the committed run
    (docs/focal_plane/emulated/y2/), its checks passing."""
    readme = " ".join((REPO / "README.md").read_text().split())
    found = re.search(rf"in the field-of-view layout \(a run: {NUMBER} \+- {NUMBER}\)", readme)
    assert found, "README: the year at two pairs is not where it was"
    result = json.loads((REPO / "docs/focal_plane/emulated/y2/requirement.json").read_text())
    headline = result["headline"]
    assert headline["consistent"] and headline["consistent_held_out"]
    assert result["settings"]["pairs_per_channel"] == 2
    expected = (headline["requirement_sigma_g1_per_k"], headline["error_per_k"])
    for value, quote in zip(expected, quoted(found[0]), strict=True):
        assert matches(value, quote), f"{quote[0]:g} vs {value:.3g}"
