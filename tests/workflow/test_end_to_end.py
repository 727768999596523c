"""The whole DAG on a tiny configuration, in a temporary directory."""

import json

import numpy as np
import pandas as pd
import pytest

pytestmark = pytest.mark.slow


def test_whole_workflow_on_tiny_config(tiny_local_run):
    workdir, result = tiny_local_run  # shared with tests/workflow/test_slurm.py
    assert result.returncode == 0, result.stderr[-4000:]
    requirement = json.loads((workdir / "results/requirement.json").read_text())
    assert np.isfinite(requirement["requirement_sigma_g1_per_k"])
    assert requirement["requirement_sigma_g1_per_k"] > 0
    assert np.isfinite(requirement["quadratic_fit"]["k_per_k2"])
    assert np.isfinite(requirement["power_law_fit"]["exponent"])
    assert [row["sigma_g1_per_k"] for row in requirement["per_sigma"]] == [1e-3, 1e-1]
    assert requirement["n_seeds"] == 2 and len(requirement["config_sha256"]) == 64
    # the template fit on the TOD path knows each seed's templates whole: it removes the
    # systematic to rounding and recovers the injected g1 exactly
    mitigated = requirement["systematic_only"]["mitigated"]
    assert mitigated["templates_known"][0].startswith("whole")
    assert 0 <= mitigated["k_per_k2"] < 1e-15 * requirement["systematic_only"]["k_per_k2"]
    assert mitigated["per_channel"]["M1-140"]["fitted_over_injected"] == pytest.approx(1, rel=1e-9)
    common = requirement["common_offset"]  # a g1 common to every detector
    assert common["k_per_k2"] > 0 and 0 < common["requirement_mu_per_k"] < np.inf
    after_fit = mitigated["common_offset"]  # the fit knows it whole too
    assert after_fit["requirement_mu_per_k"] > 1e3 * common["requirement_mu_per_k"]
    figures = sorted(p.name for p in (workdir / "results/figures").glob("*.png"))
    for number in range(1, 9):
        assert any(name.startswith(f"fig{number}_") for name in figures), figures
    # every rule wrote its log
    for rule in (
        "hwp_power",
        "kw_conversion",
        "tes_response",
        "foreground_maps",
        "tod_figures",
        "notch_effect",
        "noise_model",
        "requirement",
        "residual_spectra_figure",
    ):
        assert (workdir / f"logs/{rule}.log").exists(), rule
    # the new outputs of the analysis: both estimators and the regime
    assert isinstance(requirement["valid"], bool) and requirement["regime"]["reason"]
    assert np.isfinite(requirement["systematic_only"]["requirement_sigma_g1_per_k"])
    crossing = requirement["budget_crossing"]  # NaN when the grid does not bracket the budget
    assert len(crossing["per_seed_per_k"]) == 2 and crossing["n_seeds_crossing"] <= 2
    assert np.isfinite(crossing["sigma_g1_per_k"]) == (crossing["outside_grid"] is None)
    assert (workdir / "results/figures/requirement_vs_a2_scale.png").is_file()
    assert (workdir / "results/figures/residual_spectra_bb.png").stat().st_size > 10_000
    # the model check, both conventions, where the information and the bias come from
    headline = requirement["headline"]
    assert headline["model"] == "paper_recipe" and isinstance(headline["consistent"], bool)
    assert headline["consistent"] == requirement["consistency"]["consistent"]
    assert [row["ell"][0] for row in requirement["consistency"]["bins"]][:2] == [2, 5]
    assert np.isfinite(headline["fisher_peak_shift_requirement_sigma_g1_per_k"])
    # the report's first page: the answer, its checks, the run and the year beside it
    answer = pd.read_csv(workdir / "results/answer.csv").set_index("quantity")["value"]
    assert float(answer["sigma_g1 requirement, 68 % point [1/K]"]) == pytest.approx(
        headline["requirement_sigma_g1_per_k"], rel=1e-2
    )
    assert answer["verdict"] == headline["note"]
    assert answer["this run"].startswith("0.04 days; 2 channels")
    assert "of another analysis: likelihood_model, nside" in answer["beside the one-year answer"]
    shift = requirement["systematic_only"]["fraction_point"]
    assert len(shift["mean_delta_r"]) == len(shift["sigma_g1_per_k"]) == 21
    computed = np.array(shift["mean_delta_r"])  # NaN beyond 1e3 x the budget
    computed = computed[np.isfinite(computed)]
    assert computed.size >= 2 and np.all(np.diff(computed) > 0)  # the own power grows
    assert shift["exponent_at_smallest_sigma"] == pytest.approx(2.0, abs=0.05)
    fractions = [row["information_fraction"] for row in requirement["ell_distribution"]["bins"]]
    assert sum(fractions) == pytest.approx(1.0)
    assert (workdir / "results/figures/information_and_bias_vs_ell.png").stat().st_size > 10_000
    noise_model = (workdir / "results/spectra/noise_model.csv").read_text().splitlines()[0]
    assert "sky_transfer_bb" in noise_model
    # fixed instruments: one row each, the own power beside the linear term, a figure
    fixed = requirement["fixed_instruments"]
    assert fixed["n_instruments"] == len(fixed["instruments"]) > 1
    for row in fixed["instruments"]:
        assert row["n_seeds"] == 2 and row["k_per_k2"] > 0
        requirement_sigma, own = (
            row[f"requirement_{k}_per_k"] for k in ("sigma_g1", "quadratic_only")
        )
        if row["b_per_k"] >= 0:  # a positive linear term reaches the budget first
            assert 0 < requirement_sigma <= own * (1 + 1e-9)
    assert (workdir / "results/figures/fixed_instruments.png").stat().st_size > 10_000


def scheduled_rules(workdir, repo, *more_configfiles):
    """{rule: count} of the jobs a dry run of the tiny configuration (with more config files
    merged over it) would run."""
    from helpers import snakemake, tiny_configfiles

    result = snakemake(
        workdir, extra=("-n", "--configfile", *tiny_configfiles(repo), *more_configfiles)
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = (result.stdout + result.stderr).splitlines()
    rules = {}
    if "Nothing to be done" in result.stdout + result.stderr:
        return rules
    start = next(i for i, line in enumerate(lines) if line.startswith("job ") and "count" in line)
    for line in lines[start + 2 :]:
        parts = line.split()
        if len(parts) != 2 or not parts[1].isdigit() or parts[0] == "total":
            break
        rules[parts[0]] = int(parts[1])
    return rules


def test_figure_only_edit_reruns_no_science_job(tiny_local_run, repo):
    """Rules get only the config sections they use: after the tiny run, changing a
    figure setting schedules the figure's rule, and no simulation or analysis job."""
    workdir, result = tiny_local_run
    assert result.returncode == 0, result.stderr[-4000:]
    assert scheduled_rules(workdir, repo) == {}
    (workdir / "figures_edit.yaml").write_text("figures:\n  tod_sample_hours: 0.1\n")
    rules = scheduled_rules(workdir, repo, "figures_edit.yaml")
    assert set(rules) <= {"tod_figures", "all"}, rules
    assert rules.get("tod_figures") == 1


def test_report_builds_with_every_figure(tiny_local_run, repo):
    """`snakemake --report` on the tiny run: one HTML page with the workflow description,
    every figure and the delta r table."""
    from helpers import snakemake, tiny_configfiles

    workdir, result = tiny_local_run
    assert result.returncode == 0, result.stderr[-4000:]
    built = snakemake(
        workdir, extra=("--configfile", *tiny_configfiles(repo), "--report", "report.zip")
    )
    assert built.returncode == 0, built.stderr[-3000:]
    import zipfile

    report = zipfile.ZipFile(workdir / "report.zip")
    names = report.namelist()
    for figure in (workdir / "results/figures").glob("*.png"):
        assert any(name.endswith(figure.name) for name in names), figure.name
    assert any(name.endswith("delta_r.csv") for name in names)
    # the description and the captions render cleanly: docutils writes each warning or
    # error (e.g. an undefined |substitution|) into the HTML as a "System Message"
    pages = [name for name in names if name.endswith((".html", ".js"))]
    assert pages, names
    for name in pages:
        text = report.read(name).decode("utf-8", errors="replace")
        for marker in ("System Message:", "system-message", "docutils-error"):
            assert marker not in text, (name, marker, text[text.find(marker) - 300 :][:900])


def numbers(value, path=""):
    """{path: number} of every float and int in a JSON document."""
    if isinstance(value, dict):
        return {k: v for key in value for k, v in numbers(value[key], f"{path}/{key}").items()}
    if isinstance(value, list):
        return {
            k: v for i, item in enumerate(value) for k, v in numbers(item, f"{path}[{i}]").items()
        }
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {path: float(value)}
    return {}


def test_tiny_requirement_unchanged(tiny_local_run, repo):
    """The tiny run's requirement.json, every number, against the one committed in
    tests/data (made at the commit that moved the seeds' maps to a_lm and added the
    fixed pass's map-makers: those changes left it identical). A change that moves a
    number must say so and replace the file (python -m pytest ... then copy the run's
    results/requirement.json). What the template fit leaves on the TOD path is rounding
    (checked by test_whole_workflow_on_tiny_config), so only its keys are compared."""
    workdir, result = tiny_local_run
    assert result.returncode == 0, result.stderr[-3000:]
    produced = numbers(json.loads((workdir / "results/requirement.json").read_text()))
    expected = numbers(json.loads((repo / "tests/data/tiny_requirement.json").read_text()))
    assert set(produced) == set(expected)
    moved = {
        key: (expected[key], produced[key])
        for key in expected
        if "/mitigated/" not in key
        and not np.isclose(produced[key], expected[key], rtol=1e-6, atol=0, equal_nan=True)
    }
    assert not moved, moved


def default_workdir(tiny_default_run):
    """The tiny default run's folder, after a run that must have succeeded."""
    workdir, result = tiny_default_run
    assert result.returncode == 0, result.stderr[-3000:]
    return workdir


def test_the_default_at_tiny_size(tiny_default_run):
    """The embedded default's path (map-domain seeds, the observation sampled one chunk in
    two, the recovered-power model) at tiny size, end to end: its requirement.json and
    results/answer.csv say what the run is, pass the model checks and put it beside the
    shipped one-year answer, naming what differs."""
    workdir = default_workdir(tiny_default_run)
    requirement = json.loads((workdir / "results/requirement.json").read_text())
    headline, settings = requirement["headline"], requirement["settings"]
    assert settings["chunk_stride"] == 2 and settings["days_simulated"] == 0.0625
    assert settings["likelihood_model"] == "recovered_power" and requirement["n_seeds"] == 4
    assert headline["run"].startswith("0.125 days sampled one 0.5-hour chunk in 2")
    assert headline["consistent"] and headline["consistent_held_out"]
    beside = headline["one_year_answer"]
    assert not beside["same_analysis"]
    assert beside["differing_settings"] == ["nside", "channels", "analysis_nside"]
    answer = pd.read_csv(workdir / "results/answer.csv").set_index("quantity")["value"]
    assert answer["model check, all seeds"] == "passes"
    assert float(answer["sigma_g1 requirement, 68 % point [1/K]"]) == pytest.approx(
        headline["requirement_sigma_g1_per_k"], rel=1e-2
    )


def test_a_focal_plane_emulated_by_the_seeds_at_tiny_size(tiny_default_run, repo, tmp_path):
    """The default's path with its seeds emulating every pair of the PTEP model
    (instrument.emulated_pairs_per_channel: all; M1-140's 183 pairs from one, L1-040's 24):
    the run says so, and with the noise and the template's power both 1/183 of the
    pair's (1/24 for the noise of L1-040) sigma_r falls (measured: 326 to 22) and the
    requirement loosens (4.5e-5 to 1.5e-4 1/K)."""
    import shutil

    from helpers import TINY_DEFAULT, snakemake

    workdir = tmp_path / "emulated"  # a copy (modification times kept): only the seeds rerun
    shutil.copytree(default_workdir(tiny_default_run), workdir, symlinks=True)
    default = str(repo / TINY_DEFAULT)
    one_pair = json.loads((workdir / "results/requirement.json").read_text())
    overlay = tmp_path / "emulated.yaml"
    overlay.write_text(
        "instrument: {emulated_pairs_per_channel: all}\nmitigation: {template_fit: null}\n"
    )
    extra = ("--configfile", default, str(overlay), "--cores", "2", "--forcerun")
    result = snakemake(workdir, extra=(*extra, "map_domain_alms", "--rerun-triggers", "mtime"))
    assert result.returncode == 0, result.stderr[-3000:]
    emulated = json.loads((workdir / "results/requirement.json").read_text())
    assert emulated["settings"]["emulated_pairs_per_channel"] == "all"
    assert "their seeds emulating every pair of the channel" in emulated["headline"]["run"]
    assert (
        "emulated_pairs_per_channel"
        in emulated["headline"]["one_year_answer"]["differing_settings"]
    )
    before, after = one_pair["headline"], emulated["headline"]
    assert after["sigma_r_fisher"] < before["sigma_r_fisher"] / 5  # the noise of 24-183 pairs
    assert after["requirement_sigma_g1_per_k"] > before["requirement_sigma_g1_per_k"]
