"""Fixed instruments: g1 draws held over every seed, and the bias one focal plane carries."""

import numpy as np
import pandas as pd
import pytest

from hwp_tes_systematics.analysis import fixed_instruments as fi
from hwp_tes_systematics.analysis.likelihood import BBModel, fisher_bias
from hwp_tes_systematics.analysis.systematics import instrument_g1_draws, unit_g1_draws

DETECTORS = ["det_a", "det_b"]


def test_instrument_draws_are_fixed_and_independent_of_every_seed():
    first = instrument_g1_draws(7, "M1-140", 0, DETECTORS)
    np.testing.assert_array_equal(first, instrument_g1_draws(7, "M1-140", 0, DETECTORS))
    assert not np.allclose(first, instrument_g1_draws(7, "M1-140", 1, DETECTORS))
    assert not np.allclose(first, instrument_g1_draws(7, "M1-166", 0, DETECTORS))
    for seed in range(5):
        assert not np.allclose(first, unit_g1_draws(7, "M1-140", seed, DETECTORS))
    pair = instrument_g1_draws(7, "M1-140", 0, DETECTORS, per="pair")
    assert pair[0] == pair[1]
    with pytest.raises(ValueError, match="per"):
        instrument_g1_draws(7, "M1-140", 0, DETECTORS, per="focal_plane")


@pytest.mark.parametrize("b", [0.0, 3e-4, -3e-4, -3e-3])
def test_budget_sigma_is_the_first_crossing_of_the_budget(b):
    """|2 sigma b + sigma^2 k| reaches the budget at the returned sigma and nowhere below."""
    k, budget = 1.0, 6.5e-6
    sigma = fi.budget_sigma(b, k, budget)
    assert abs(2 * sigma * b + sigma**2 * k) == pytest.approx(budget, rel=1e-9)
    below = np.linspace(0, sigma, 10_001)[:-1]
    assert np.all(np.abs(2 * below * b + below**2 * k) < budget)
    if b == 0.0:
        assert sigma == pytest.approx(np.sqrt(budget / k))
    if b == -3e-3:  # the dip reaches -budget first: the linear term sets it
        assert sigma < np.sqrt(budget / k)


def _model(lmax=40):
    ell = np.arange(lmax + 1)
    return BBModel(ell, 1e-18, 1e-16 / (1 + ell), 0.0, 1e-17, 0.5)


def _tables(model, cross_mean, n_seeds, scatter, rng, n_instruments=2):
    """Seeds' instrument tables: auto = C_GW shape, cross = cross_mean x shape + noise."""
    shape = model.c_gw_r1
    tables = []
    for _ in range(n_seeds):
        table = {"ell": model.ell}
        for index in range(n_instruments):
            table[fi.AUTO.format(index=index)] = 4.0 * shape
            noise = rng.normal(scale=scatter) * shape
            table[fi.CROSS.format(index=index)] = cross_mean[index] * shape + noise
            table[fi.CROSS_UNFILTERED.format(index=index)] = 0.0 * shape
        tables.append(pd.DataFrame(table))
    return tables


def test_a_resolved_linear_term_sets_the_requirement():
    """An instrument whose cross spectrum has a mean far above its seed scatter: b is that
    mean's Fisher bias, |t| > 2, and the requirement is tighter than the own power's; an
    instrument with a zero-mean cross spectrum keeps (nearly) the own power's."""
    model = _model()
    rng = np.random.default_rng(3)
    tables = _tables(model, [5e-3, 0.0], 40, 1e-4, rng)
    result = fi.fixed_instrument_estimator(tables, model, 6.5e-6)
    strong, null = result["instruments"]
    expected_b = fisher_bias(5e-3 * model.c_gw_r1, model)
    assert strong["b_per_k"] == pytest.approx(expected_b, rel=0.01)
    assert abs(strong["t_linear"]) > 20 and abs(null["t_linear"]) < 4
    assert strong["k_per_k2"] == pytest.approx(fisher_bias(4.0 * model.c_gw_r1, model))
    assert strong["requirement_sigma_g1_per_k"] < 0.5 * strong["requirement_quadratic_only_per_k"]
    assert null["requirement_debiased_per_k"] == pytest.approx(
        null["requirement_quadratic_only_per_k"], rel=0.05
    )
    assert result["fraction_linear_resolved"] == 0.5
    # the unfiltered residual's cross spectra (all zero here) give the own power alone
    unfiltered = fi.fixed_instrument_estimator(tables, model, 6.5e-6, unfiltered=True)
    for row in unfiltered["instruments"]:
        assert row["requirement_sigma_g1_per_k"] == pytest.approx(
            row["requirement_quadratic_only_per_k"]
        )


def test_tables_with_different_instrument_counts_are_refused():
    model = _model()
    rng = np.random.default_rng(4)
    tables = _tables(model, [0.0, 0.0], 2, 1e-4, rng)
    tables[1] = tables[1].drop(columns=[fi.AUTO.format(index=1)])
    with pytest.raises(ValueError, match="instruments"):
        fi.instrument_biases(tables, model)


def test_requirement_stage_summarises_and_draws_the_instruments(tmp_path):
    """The requirement stage's summary of the seeds' CSVs: the JSON block and the figure;
    no instruments (fixed_instruments: 0): no block."""
    from hwp_tes_systematics.stages.requirement import fixed_instruments

    model = _model()
    rng = np.random.default_rng(5)
    paths = []
    for seed, table in enumerate(_tables(model, [5e-3, 0.0, -1e-3], 4, 1e-4, rng, 3)):
        paths.append(tmp_path / f"seed{seed}.csv")
        table.to_csv(paths[-1], index=False)
    figure = tmp_path / "fixed_instruments.png"
    own = {"k_per_k2": 1.0}
    fixed = fixed_instruments(paths, model, 6.5e-6, "paper_recipe", own, str(figure), None)
    assert fixed["n_instruments"] == 3 and fixed["residual"] == "filtered CMB reference"
    assert figure.stat().st_size > 10_000
    empty = tmp_path / "empty.csv"
    pd.DataFrame({"ell": model.ell}).to_csv(empty, index=False)
    assert fixed_instruments([empty], model, 6.5e-6, "paper_recipe", own, None, None) is None


def test_the_68_percent_convention_matches_the_likelihood_at_the_crossing():
    """delta r_68 = 2 sigma b68 + sigma^2 k68 from one shift per term: at the returned
    requirement the 68 % point of the whole spectrum (no-systematics residual + 2 sigma
    cross + sigma^2 auto), found numerically, has moved by the budget; the linear term
    scales linearly (the regime the coefficients rest on)."""
    from hwp_tes_systematics.analysis.likelihood import fraction_point_shift

    model = _model()
    rng = np.random.default_rng(5)
    tables = _tables(model, [5e-3, 0.0], 40, 1e-4, rng)
    c_res = model.n_ell + model.c_lens  # a no-systematics residual the model describes
    budget = 6.5e-6
    result = fi.fixed_instrument_estimator(tables, model, budget, c_res_nosys=c_res)
    assert result["fraction_point"]["linearity_check"] == pytest.approx(1.0, abs=0.01)
    for index, row in enumerate(result["instruments"]):
        sigma = row["requirement_68_per_k"]
        cross = np.mean([t[fi.CROSS.format(index=index)] for t in tables], axis=0)
        auto = np.mean([t[fi.AUTO.format(index=index)] for t in tables], axis=0)
        (shift,) = fraction_point_shift(c_res, 2 * sigma * cross + sigma**2 * auto, model, [1.0])
        assert abs(shift) == pytest.approx(budget, rel=0.02)
        # the 68 % point moves less than the Fisher peak per unit spectrum here (r >= 0)
        assert 0 < row["k68_per_k2"] < row["k_per_k2"] * 1.5
    strong = result["instruments"][0]
    assert strong["requirement_68_per_k"] < strong["requirement_68_quadratic_only_per_k"]


def test_split_half_correlation_tells_a_real_linear_term_from_noise():
    """b from the even seeds against b from the odd seeds: instruments whose cross spectra
    have different true means correlate; zero-mean cross spectra (estimation noise only)
    do not."""
    model = _model()
    rng = np.random.default_rng(6)
    real = rng.normal(scale=5e-3, size=30)
    tables = _tables(model, real, 20, 1e-3, rng, n_instruments=30)
    assert fi.split_half_correlation(tables, model)["pearson_r"] > 0.9
    null = fi.split_half_correlation(_tables(model, np.zeros(30), 20, 1e-3, rng, 30), model)
    assert abs(null["pearson_r"]) < 0.6 and null["p_value"] > 1e-3
    assert np.isnan(fi.split_half_correlation(tables[:3], model)["pearson_r"])


def test_common_offset_requirement_and_the_region_it_shares_with_the_random_population():
    """A g1 common to every detector: |mu| < budget_sigma(b, k); with a random population
    at a fraction f of its own requirement beside it, the budget left is (1 - f^2) B and
    the allowed |mu| shrinks accordingly (to sqrt(B / k) x sqrt(1 - f^2) when b = 0)."""
    model = _model()
    shape = model.c_gw_r1
    k_unit = fisher_bias(shape, model)
    tables = [
        pd.DataFrame(
            {
                "ell": model.ell,
                fi.COMMON_AUTO: 8.0 * shape,
                fi.COMMON_CROSS: 0.0 * shape,
                fi.COMMON_CROSS_UNFILTERED: 0.0 * shape,
            }
        )
        for _ in range(3)
    ]
    budget, k_random = 6.5e-6, 2.0 * k_unit
    common = fi.common_offset_estimator(tables, model, budget, k_random)
    assert common["k_per_k2"] == pytest.approx(8.0 * k_unit)
    assert common["k_over_k_random"] == pytest.approx(4.0)
    assert common["requirement_mu_per_k"] == pytest.approx(np.sqrt(budget / (8.0 * k_unit)))
    for row in common["allowed_region"]:
        f = row["sigma_over_requirement"]
        expected = np.sqrt(budget * (1 - f**2) / (8.0 * k_unit))
        assert row["mu_max_per_k"] == pytest.approx(expected)
    assert (
        fi.common_offset_estimator(
            [t.drop(columns=fi.COMMON_AUTO) for t in tables], model, budget, k_random
        )
        is None
    )
    # a common offset of either sign: the requirement is the sign that reaches the budget
    # first, the same for a cross spectrum of either sign
    for sign in (1.0, -1.0):
        for table in tables:
            table[fi.COMMON_CROSS] = sign * 3e-3 * shape
        common = fi.common_offset_estimator(tables, model, budget, k_random)
        b, k = common["b_per_k"], common["k_per_k2"]
        assert np.sign(b) == sign
        for mu in (common["requirement_mu_per_k"], -common["requirement_mu_per_k"]):
            assert abs(2 * mu * b + mu**2 * k) <= budget * (1 + 1e-9)
        assert common["requirement_mu_per_k"] == pytest.approx(fi.budget_sigma(abs(b), k, budget))
        assert common["requirement_mu_per_k"] < fi.budget_sigma(-abs(b), k, budget)


def test_a_common_offset_the_template_fit_removes_whole_has_no_requirement():
    """After the template fit (columns COMMON_MITIGATED): a leftover at rounding (k <= 0,
    b = 0) sets no bound; a linear term alone (k = 0) gives B / 2|b|."""
    model = _model()
    shape = model.c_gw_r1
    auto, cross, cross_unfiltered = fi.common_columns(fi.COMMON_MITIGATED)
    tables = [
        pd.DataFrame(
            {"ell": model.ell, auto: -1e-30 * shape, cross: 0 * shape, cross_unfiltered: 0 * shape}
        )
        for _ in range(3)
    ]
    budget = 6.5e-6
    after = fi.common_offset_estimator(tables, model, budget, 0.0, name=fi.COMMON_MITIGATED)
    assert after["requirement_mu_per_k"] == np.inf
    assert after["random_requirement_sigma_per_k"] == np.inf
    assert fi.common_offset_estimator(tables, model, budget, 1.0) is None  # no COMMON columns
    assert fi.budget_sigma(-2e-3, 0.0, budget) == pytest.approx(budget / 4e-3)
    with pytest.raises(ValueError, match="k >= 0"):
        fi.budget_sigma(1e-3, -1.0, budget)
