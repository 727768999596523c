"""Requirement on sigma_g1: delta r, summaries over seeds, quadratic and power-law fits,
edge cases, and the Fig. 8 figure."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from hwp_tes_systematics import config as cfg
from hwp_tes_systematics.analysis import requirement as rq
from hwp_tes_systematics.figures.results import plot_requirement

SIGMAS = np.logspace(-4, -1, 4)  # the paper's sigma_g1 grid [1/K]
K_PAPER = 6.5e-6 / 2e-3**2  # the k [K^2] giving the paper's requirement 2e-3 K^-1


def test_delta_r():
    assert rq.delta_r([0.1, 0.2], [0.3, 0.1]) == pytest.approx([0.2, 0.1])
    assert rq.delta_r(1e-3, 1e-3) == 0.0


def test_summarise_dataframe_and_mapping():
    table = pd.DataFrame(
        {
            "sigma_g1": [1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 0.0],
            "seed": [0, 1, 2, 0, 1, 0],
            "delta_r": [1.0, 2.0, 3.0, 10.0, 14.0, 0.5],
        }
    )
    summary = rq.summarise(table)
    assert list(summary.columns) == list(rq.SUMMARY_COLUMNS)
    assert summary["sigma_g1"].tolist() == [0.0, 1e-3, 1e-2]
    row = summary.iloc[1]
    assert row["mean_delta_r"] == pytest.approx(2.0)
    assert row["std_delta_r"] == pytest.approx(1.0)  # sample std (ddof = 1)
    assert row["sem_delta_r"] == pytest.approx(1.0 / np.sqrt(3))
    assert row["n_seeds"] == 3
    assert np.isnan(summary.iloc[0]["std_delta_r"])  # one seed
    same = rq.summarise({1e-2: [10.0, 14.0], 1e-3: [1.0, 2.0, 3.0], 0.0: 0.5})
    pd.testing.assert_frame_equal(same, summary)
    with pytest.raises(ValueError, match="missing columns"):
        rq.summarise(table.drop(columns="delta_r"))


def test_fit_quadratic_exact_and_requirement():
    delta = K_PAPER * SIGMAS**2
    assert rq.fit_quadratic(SIGMAS, delta) == pytest.approx(K_PAPER, rel=1e-12)
    weights = [1.0, 4.0, 9.0, 16.0]
    assert rq.fit_quadratic(SIGMAS, delta, weights) == pytest.approx(K_PAPER, rel=1e-12)
    assert rq.requirement_sigma(K_PAPER) == pytest.approx(2e-3, rel=1e-12)
    assert rq.requirement_sigma(4.0, budget=1e-2) == pytest.approx(np.sqrt(1e-2 / 4.0))
    assert rq.DELTA_R_BUDGET == 6.5e-6
    with pytest.raises(ValueError, match="k = "):
        rq.requirement_sigma(0.0)


def test_fit_quadratic_log_space_weights():
    """Log-space fit: ln k is the weighted mean of ln(delta r / sigma^2)."""
    ratios = np.array([1.0, 2.0, 4.0, 8.0])
    delta = ratios * SIGMAS**2
    assert rq.fit_quadratic(SIGMAS, delta) == pytest.approx(np.exp(np.mean(np.log(ratios))))
    w = np.array([1.0, 0.0001, 0.0001, 0.0001])
    assert rq.fit_quadratic(SIGMAS, delta, w) == pytest.approx(1.0, rel=1e-3)
    w = rq.log_weights_from_sem(delta, 0.1 * delta)
    assert np.allclose(w, 100.0)


def test_fit_power_law_exact():
    amplitude, exponent, exponent_sigma = rq.fit_power_law(SIGMAS, K_PAPER * SIGMAS**2)
    assert abs(exponent - 2.0) < 1e-10
    assert amplitude == pytest.approx(K_PAPER, rel=1e-9)
    assert exponent_sigma < 1e-9
    _, exponent3, _ = rq.fit_power_law(SIGMAS, 0.5 * SIGMAS**3)
    assert exponent3 == pytest.approx(3.0, abs=1e-10)
    _, _, two_point_sigma = rq.fit_power_law(SIGMAS[:2], SIGMAS[:2] ** 2)
    assert np.isnan(two_point_sigma)  # no degrees of freedom left


def test_edge_cases():
    sigma = np.concatenate([[0.0], SIGMAS])
    delta = np.concatenate([[1e-9], K_PAPER * SIGMAS**2])
    # sigma = 0 (no-systematics reference) is excluded silently
    assert rq.fit_quadratic(sigma, delta) == pytest.approx(K_PAPER, rel=1e-12)
    bad = delta.copy()
    bad[1] = 0.0
    bad[2] = -1e-7
    with pytest.warns(RuntimeWarning, match="non-positive"):
        assert rq.fit_quadratic(sigma, bad) == pytest.approx(K_PAPER, rel=1e-12)
    with pytest.warns(RuntimeWarning, match="non-positive"):
        _, exponent, _ = rq.fit_power_law(sigma, bad)
    assert exponent == pytest.approx(2.0, abs=1e-10)
    bad[3] = np.nan
    with pytest.warns(RuntimeWarning), pytest.raises(ValueError, match="at least 2"):
        rq.fit_quadratic(sigma, bad)
    with pytest.raises(ValueError, match="at least 2"):
        rq.fit_power_law([0.0, 1e-3], [1e-9, 1e-6])
    with pytest.raises(ValueError, match="differ"):
        rq.fit_quadratic(SIGMAS, SIGMAS[:3])


def test_noisy_two_seeds_finite():
    rng = np.random.default_rng(1)
    rows = [
        {"sigma_g1": s, "seed": seed, "delta_r": K_PAPER * s**2 * rng.lognormal(0.0, 0.5)}
        for s in SIGMAS
        for seed in range(2)
    ]
    summary = rq.summarise(pd.DataFrame(rows))
    assert (summary["n_seeds"] == 2).all()
    weights = rq.log_weights_from_sem(summary["mean_delta_r"], summary["sem_delta_r"])
    k = rq.fit_quadratic(summary["sigma_g1"], summary["mean_delta_r"], weights)
    amplitude, exponent, exponent_sigma = rq.fit_power_law(
        summary["sigma_g1"], summary["mean_delta_r"]
    )
    values = [k, amplitude, exponent, exponent_sigma, rq.requirement_sigma(k)]
    assert np.all(np.isfinite(values))
    assert 0.2 * K_PAPER < k < 5 * K_PAPER
    assert abs(exponent - 2.0) < 0.3


def test_plot_requirement(tmp_path):
    rng = np.random.default_rng(2)
    mean = K_PAPER * SIGMAS**2 * rng.lognormal(0.0, 0.2, SIGMAS.size)
    std = 0.5 * mean
    std[0] = np.nan  # one seed: no bar
    k = rq.fit_quadratic(SIGMAS, mean)
    _, exponent, exponent_sigma = rq.fit_power_law(SIGMAS, mean)
    path = plot_requirement(
        SIGMAS,
        mean,
        std,
        k,
        exponent,
        rq.DELTA_R_BUDGET,
        rq.requirement_sigma(k),
        tmp_path / "sub" / "fig8.png",
        exponent_sigma=exponent_sigma,
    )
    assert path.is_file() and path.stat().st_size > 1000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(path.parent.glob(".*tmp*"))  # written atomically, no leftovers


def linear_points_figure(path) -> tuple[tuple, dict]:
    """plot_requirement's arguments for points that grow as sigma^0.5 (the sigma^2 model
    invalid, their budget crossing marked) beside a systematic-only estimator."""
    mean = 1e-4 * (SIGMAS / 0.1) ** 0.5
    arguments = (SIGMAS, mean, 0.3 * mean, rq.fit_quadratic(SIGMAS, mean), 0.5)
    options = {
        "invalid_reason": "the points do not follow sigma^2: exponent 0.50",
        "crossing": rq.budget_crossing(SIGMAS, mean),
        "systematic_only": (SIGMAS, K_PAPER * SIGMAS**2, 0.1 * K_PAPER * SIGMAS**2, K_PAPER, 2e-3),
    }
    return (*arguments, rq.DELTA_R_BUDGET, None, path), options


def test_plot_requirement_labels_cover_nothing(tmp_path, monkeypatch):
    """Fig. 8: every requirement's value is in the legend, below the axes; no text inside
    the data area (where it could cover a point, a line or another label)."""
    from hwp_tes_systematics.figures import results

    drawn = {}

    def keep(figure, path):
        figure.canvas.draw()
        drawn["figure"] = figure

    monkeypatch.setattr(results, "save_figure", keep)
    arguments, options = linear_points_figure(tmp_path / "fig8.png")
    results.plot_requirement(
        *arguments,
        **options,
        quadratic_threshold=1e-4,
        fraction_point=(SIGMAS, 0.5 * K_PAPER * SIGMAS**2, 2.8e-3),
    )
    figure = drawn["figure"]
    (axis,) = figure.axes
    assert len(axis.texts) == 0  # nothing written over the data
    legend = axis.get_legend()
    labels = [text.get_text() for text in legend.get_texts()]
    for value in ("0.002", "0.0028", f"{options['crossing']:.2g}"):
        assert any(f"sigma_g1 < {value} K^-1" in label for label in labels), value
    renderer = figure.canvas.get_renderer()
    axes_box = axis.get_window_extent(renderer)
    legend_box = legend.get_window_extent(renderer)
    assert legend_box.y1 < axes_box.y0  # the legend lies below the axes
    assert figure.bbox.contains(legend_box.x0, legend_box.y0)  # and inside the figure


def test_regime_accepts_sigma_squared_and_flags_other_exponents():
    sigma_r = 1e-2
    quadratic = rq.assess_quadratic_regime(SIGMAS, 1e-3 * (SIGMAS / 0.1) ** 2, sigma_r)
    assert quadratic["valid"] and quadratic["sigma2_model_consistent"]
    assert quadratic["free_exponent"] == pytest.approx(2.0)
    assert quadratic["k_per_k2"] == pytest.approx(1e-3 / 0.1**2)
    # delta r ~ sigma^0.5, all points well inside the quadratic regime: invalid
    root = rq.assess_quadratic_regime(SIGMAS, 1e-4 * (SIGMAS / 0.1) ** 0.5, sigma_r)
    assert not root["valid"] and not root["sigma2_model_consistent"]
    assert root["free_exponent"] == pytest.approx(0.5)
    assert "do not follow sigma^2" in root["reason"]
    # every point beyond 0.1 sigma_r: invalid, k from all points, and it says why
    saturated = rq.assess_quadratic_regime(SIGMAS, np.full(4, 0.5 * sigma_r), sigma_r)
    assert not saturated["valid"] and saturated["sigma_g1_in_quadratic_regime_per_k"] == []
    assert "not reached" in saturated["reason"]


def test_plot_requirement_says_when_invalid(tmp_path):
    arguments, options = linear_points_figure(tmp_path / "fig8.png")
    path = plot_requirement(*arguments, **options)
    assert path.stat().st_size > 1000


def test_budget_crossing_interpolates_a_power_law_exactly():
    # delta r = 3e-5 sigma (linear, the one-year regime): reaches 6.5e-6 at sigma = 0.2167
    sigmas = np.array([1e-3, 1e-2, 1e-1, 1.0])
    linear = 3e-5 * sigmas
    assert rq.budget_crossing(sigmas, linear) == pytest.approx(rq.DELTA_R_BUDGET / 3e-5)
    # a curve bending between grid points: interpolated as a power law between them
    bent = np.array([1e-9, 1e-8, 1e-6, 1e-4])
    expected = 1e-1 * (rq.DELTA_R_BUDGET / 1e-6) ** (1 / 2)  # slope 2 from (0.1, 1e-6)
    assert rq.budget_crossing(sigmas, bent) == pytest.approx(expected)
    # never bracketed: NaN (below the budget everywhere, or above it from the start)
    assert np.isnan(rq.budget_crossing(sigmas, 1e-9 * sigmas))
    assert np.isnan(rq.budget_crossing(sigmas, 1.0 + sigmas))
    # ... and the side of the grid it lies on is said in words
    assert rq.crossing_outside_grid(sigmas, bent) is None
    assert rq.crossing_outside_grid(sigmas, 1e-9 * sigmas).startswith("above the grid")
    below = rq.crossing_outside_grid(sigmas, 1.0 + sigmas)
    assert below.startswith("below the grid") and f"{sigmas.min():.3g}" in below


def test_budget_crossing_over_seeds():
    sigmas = [1e-2, 1e-1, 1.0]
    rows = [
        {"seed": seed, "sigma_g1": s, "delta_r": scale * 1e-5 * s}
        for seed, scale in enumerate([1.0, 2.0, 4.0])
        for s in sigmas
    ]
    crossing = rq.budget_crossing_over_seeds(pd.DataFrame(rows))
    per_seed = rq.DELTA_R_BUDGET / (1e-5 * np.array([1.0, 2.0, 4.0]))
    assert crossing["per_seed_per_k"] == pytest.approx(per_seed)
    assert crossing["std_over_seeds_per_k"] == pytest.approx(np.std(per_seed, ddof=1))
    assert crossing["sigma_g1_per_k"] == pytest.approx(rq.DELTA_R_BUDGET / (1e-5 * 7 / 3))
    assert crossing["n_seeds_crossing"] == 3


def test_bootstrap_error_is_the_error_of_the_mean():
    from hwp_tes_systematics.analysis.systematic_only import bootstrap_error

    values = np.random.default_rng(3).normal(10.0, 2.0, size=400)
    error = bootstrap_error(values, np.mean)
    assert error == pytest.approx(2.0 / np.sqrt(400), rel=0.15)
    assert bootstrap_error(np.full(20, 3.0), np.mean) == 0.0
    assert np.isnan(bootstrap_error(np.ones(1), np.mean))


def test_template_split_shares_sum_to_one_and_drop_the_noise_part(tmp_path):
    """The requirement stage's template split: the pairs' k sum to the k of their summed
    BB; without the noise x h pairs the requirement loosens; no split columns: None."""
    from hwp_tes_systematics.analysis.channel_alms import TEMPLATE_PARTS
    from hwp_tes_systematics.analysis.likelihood import BBModel, fisher_bias
    from hwp_tes_systematics.analysis.systematic_only import template_split

    ell = np.arange(41)
    model = BBModel(ell, 1e-18, 1e-16 / (1 + ell), 0.0, 1e-17, 0.5)
    rng = np.random.default_rng(2)
    pairs = [(a, b) for i, a in enumerate(TEMPLATE_PARTS) for b in TEMPLATE_PARTS[i:]]
    paths, total = [], 0.0
    for seed in range(3):
        table = {"ell": ell}
        for a, b in pairs:
            table[f"bb_{a}_x_{b}_k4"] = rng.uniform(0.5, 1.5) * 1e-17 / (1 + ell)
            total = total + (1 if a == b else 2) * table[f"bb_{a}_x_{b}_k4"] / 3
        paths.append(tmp_path / f"seed{seed}.csv")
        pd.DataFrame(table).to_csv(paths[-1], index=False)
    split = template_split([pd.read_csv(path) for path in paths], model, 6.5e-6)
    assert sum(split["k_per_k2"].values()) == pytest.approx(fisher_bias(total, model))
    assert sum(split["fraction_of_k"].values()) == pytest.approx(1.0)
    assert split["requirement_without_noise_h_per_k"] > np.sqrt(6.5e-6 / fisher_bias(total, model))
    old = pd.DataFrame({"ell": ell, "bb_unit_k4": 1e-17})
    assert template_split([old], model, 6.5e-6) is None


def test_figure8_command_redraws_a_committed_run(tmp_path, capsys):
    """``python -m hwp_tes_systematics figure8`` redraws Fig. 8 from a run's files (the
    committed one-year run), and names the file or the argument when one is not what it
    expects, before any work."""
    import shutil

    from hwp_tes_systematics.cli import main

    def status_of(*argv):
        try:
            return main([str(a) for a in argv])
        except SystemExit as exit:  # argparse's errors
            return exit.code

    run = Path(__file__).parents[2] / "docs" / "one_year"
    out = tmp_path / "fig8.png"
    assert status_of("figure8", run / "requirement.json", "--out", out) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    not_json = tmp_path / "notes.txt"
    not_json.write_text("not a requirement")
    assert status_of("figure8", not_json, "--out", tmp_path / "x.png") == 2
    assert "argument --delta-r: no " in capsys.readouterr().err  # nothing beside it
    shutil.copy(run / "delta_r.csv", tmp_path / "delta_r.csv")
    assert status_of("figure8", not_json, "--out", tmp_path / "x.png") == 2
    assert "notes.txt" in capsys.readouterr().err
    assert status_of("figure8", tmp_path / "absent.json", "--out", out) == 2
    assert "absent.json: no such file" in capsys.readouterr().err
    assert status_of("figure8", run / "requirement.json", "--out", tmp_path / "fig8.svg") == 2
    assert "fig8.svg: expected a file name ending in .png" in capsys.readouterr().err


def test_a_run_says_what_it_is_and_where_it_stands_beside_the_year(default_config):
    """requirement.json's headline names the run (its days, channels, seeds, maps) and
    puts its answer beside the shipped one-year answer when the two are one analysis."""
    import copy

    from hwp_tes_systematics.analysis import run_summary as stage

    year = copy.deepcopy(default_config)
    year["simulation"].update(
        seeds=20, duration_days=365.25, chunk_stride=1, noise_scale=1.0, realizations="map_domain"
    )
    year["likelihood"]["model"] = "recovered_power"
    one_in_ten = copy.deepcopy(year)
    one_in_ten["simulation"].update(chunk_stride=10, noise_scale=0.3162)
    assert stage.days_simulated(year) == 365.25
    assert stage.days_simulated(one_in_ten) == 37.0  # days 0, 10, ..., 360
    sampled = stage.run_settings(one_in_ten)
    assert "one day in 10 (37 days simulated" in stage.describe_run(one_in_ten)
    assert "22 channels" in stage.describe_run(one_in_ten)

    shipped = json.loads(cfg.one_year_requirement_path().read_text())
    answer = shipped["headline"]["requirement_sigma_g1_per_k"]
    beside = stage.one_year_comparison({"requirement_sigma_g1_per_k": answer / 2}, sampled)
    assert beside["same_analysis"] and beside["differing_settings"] == []
    assert beside["one_year_over_this_run"] == pytest.approx(2.0)
    assert "2.00 times this run's" in beside["note"]
    itself = stage.one_year_comparison(shipped["headline"], stage.run_settings(year))
    assert itself["note"] == "the one-year answer's configuration: ratio 1.000"

    other = copy.deepcopy(one_in_ten)
    other["maps"]["baseline_length_s"] = None
    other["likelihood"]["model"] = "paper_recipe"
    apart = stage.one_year_comparison(
        {"requirement_sigma_g1_per_k": 1e-5}, stage.run_settings(other)
    )
    assert not apart["same_analysis"] and "one_year_over_this_run" not in apart
    assert apart["differing_settings"] == ["baseline_length_s", "likelihood_model"]
