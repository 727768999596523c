"""Likelihood of r (Hamimeche & Lewis form of the study): recovery of r, 68 % points vs
Fisher, delta r ~ sigma^2 on synthetic residual spectra, grids, bad inputs, Fig. 7."""

import numpy as np
import pytest

from hwp_tes_systematics.analysis import likelihood as lk
from hwp_tes_systematics.analysis.requirement import fit_power_law, fit_quadratic
from hwp_tes_systematics.figures.results import plot_likelihoods, sigma_label

LMAX = 200
F_SKY = 0.5
DEPTH_UK_ARCMIN = 2.0  # LiteBIRD-like polarisation depth after component separation
FWHM_ARCMIN = 30.0
N_GRID = 5001  # coarser than the default for speed (adaptive_r_grid refines if needed)
SIGMAS = np.logspace(-4, -1, 4)  # the paper's sigma_g1 grid [1/K]


def foreground_residual(ell, d80_uk2=1e-5, slope=-2.5):
    """Assumed foreground residual: C_ell = C_80 (ell / 80)^slope, D_80 = d80 uK^2 (K^2).

    D_80 = 1e-5 uK^2 with this slope gives D_2 ~ 1e-4 uK^2 ~ the r = 6e-3 tensor BB at
    ell = 2 (order of the LiteBIRD post-component-separation residual at low ell).
    """
    c80 = d80_uk2 * 1e-12 * 2 * np.pi / (80 * 81)
    out = np.zeros(ell.size)
    out[2:] = c80 * (ell[2:] / 80.0) ** slope
    return out


@pytest.fixture(scope="module")
def ell():
    return np.arange(LMAX + 1)


@pytest.fixture(scope="module")
def noise(ell):
    return lk.white_noise_bb(ell, DEPTH_UK_ARCMIN, FWHM_ARCMIN)


@pytest.fixture(scope="module")
def model(ell, noise):
    """LiteBIRD-like: PTEP lensing and tensor BB, 2 uK-arcmin, 30', f_sky 0.5, ell 2..200."""
    return lk.BBModel.from_ptep(
        F_SKY, lmin=2, lmax=LMAX, n_ell=noise, c_fg_res=foreground_residual(ell)
    )


@pytest.fixture(scope="module")
def model_no_fg(noise):
    return lk.BBModel.from_ptep(F_SKY, lmin=2, lmax=LMAX, n_ell=noise)


def test_white_noise_spectrum(ell):
    n = lk.white_noise_bb(ell, 2.0, 30.0)
    white = (2e-6 * np.pi / 180 / 60) ** 2  # (2 uK arcmin)^2 in K^2 sr
    assert n[0] == pytest.approx(white, rel=1e-12)
    sigma_b = np.radians(0.5) / np.sqrt(8 * np.log(2))
    assert n[200] == pytest.approx(white * np.exp(200 * 201 * sigma_b**2), rel=1e-12)
    assert np.all(lk.white_noise_bb(ell, 2.0, 0.0) == pytest.approx(white))


def test_minus_two_log_likelihood_is_equation_1(model, noise, ell):
    """The deviance + constant rewrite equals eq. (1) summed term by term."""
    c_obs = model.c_obs_from_residual(0.003 * model.c_gw_r1 + 1.3 * noise)
    rs = np.array([0.0, 1e-3, 0.01, 0.1])
    got = lk.minus_two_log_likelihood(rs, c_obs, model)
    sel = (ell >= 2) & (ell <= LMAX)
    for r, value in zip(rs, got):
        c_mod = (r * model.c_gw_r1 + model.c_lens + model.c_fg_res + model.n_ell)[sel]
        co, el = c_obs[sel], ell[sel]
        brute = np.sum(
            (2 * el + 1)
            * F_SKY
            * (np.log(c_mod) + co / c_mod - (2 * el - 1) / (2 * el + 1) * np.log(co))
        )
        assert value == pytest.approx(brute, rel=1e-12, abs=1e-6)
    # the (2l-1)/(2l+1) ln C_obs term does not depend on r: the deviance differs by a constant
    diff = got - lk.deviance(rs, c_obs, model)
    assert np.ptp(diff) < 1e-6 * np.max(np.abs(diff))
    assert got.shape == rs.shape


def test_ml_recovers_r_in(model, noise):
    """C_obs = C_mod(r_in = 0.01): the maximum of L is at r_in (eq. 1 is minimal at
    C_mod = C_obs)."""
    r_in = 0.01
    c_res = r_in * model.c_gw_r1 + model.c_fg_res + noise
    result = lk.fit_r(c_res, model)
    assert abs(result.r_ml - r_in) < 1e-4
    assert abs(result.r_ml - r_in) < 1e-3 * result.sigma_r_fisher_ml  # parabolic refinement
    c_obs = model.c_obs_from_residual(c_res)
    assert lk.deviance(r_in, c_obs, model) == pytest.approx(0.0, abs=1e-12)
    # the 68 % point lies above the peak, by less than one Fisher width at the peak
    assert r_in < result.r_fraction < r_in + result.sigma_r_fisher_ml
    assert np.trapezoid(result.likelihood, result.r_grid) == pytest.approx(1.0, rel=1e-12)


def test_r68_of_r_in_zero_is_fisher_upper_bound(model, noise):
    """r_in = 0: the 68 % point is an upper bound close to the half-normal 0.9945 sigma_r.

    -2 ln L(r) <= r^2 / sigma_r(0)^2 (each ell adds ln(1 + u) - u / (1 + u) <= u^2 / 2,
    u = r C_GW / C_mod(0)), with a ratio L / Gaussian increasing in r: r68 is at least the
    half-normal value 0.9945 sigma_r(0), and close to it when u(r68) << 1.
    """
    assert lk.half_normal_quantile(0.68) == pytest.approx(0.99446, abs=1e-5)
    result = lk.fit_r(model.c_fg_res + noise, model, n=N_GRID)
    sigma_r = model.fisher_sigma_r(0.0)
    assert result.r_ml == 0.0
    ratio = result.r_fraction / (lk.half_normal_quantile(0.68) * sigma_r)
    assert 0.5 <= result.r_fraction / sigma_r <= 1.5
    assert 1.0 <= ratio < 1.1, ratio


def test_r68_without_foreground_residual_is_non_gaussian(model_no_fg, noise):
    """Caveat: without C_FGres the reionisation bump is cosmic-variance limited from
    r ~ 1e-5 (C_GW^{r=1} / N ~ 5e4 at ell = 2), the likelihood is far from Gaussian and
    r68 ~ 2 sigma_r(0) (Fisher at r = 0 overstates the precision)."""
    result = lk.fit_r(noise, model_no_fg, n=N_GRID)
    sigma_r = model_no_fg.fisher_sigma_r(0.0)
    assert result.r_fraction >= lk.half_normal_quantile(0.68) * sigma_r
    assert 1.8 < result.r_fraction / sigma_r < 2.2


def test_gaussian_limit_half_normal():
    """Weak tensor signal (u = r C_GW / C_mod << 1): L is a half-Gaussian of width sigma_r."""
    ell = np.arange(2, 401)
    model = lk.BBModel(
        ell=ell, c_lens=1.0, c_gw_r1=1e-3, c_fg_res=0.0, n_ell=1.0, f_sky=1.0, lmin=2
    )
    sigma_r = model.fisher_sigma_r(0.0)
    result = lk.fit_r(2.0 - model.c_lens, model, n=N_GRID)  # C_obs = C_mod(0) = 2
    assert result.r_fraction == pytest.approx(lk.half_normal_quantile(0.68) * sigma_r, rel=0.01)


def test_delta_r_grows_as_sigma_squared(model, noise, ell):
    """C_res(sigma) = C_FGres + N + sigma^2 T: r68(sigma) - r68(0) ~ sigma^2 over 1e-4..1e-1.

    T is white with amplitude N_2 (the noise at ell = 2), so that at sigma = 0.1
    delta r ~ 0.04 sigma_r (linear-response regime): exponent 2 to a few 1e-3 (with
    3 N_2, delta r ~ 0.13 sigma_r, it is already 2.01).
    """
    template = np.full(ell.size, noise[2])
    base = model.c_fg_res + noise
    delta = []
    for sigma in SIGMAS:
        sys, nosys = lk.fit_r_common_grid([base + sigma**2 * template, base], model, n=N_GRID)
        delta.append(sys.r_fraction - nosys.r_fraction)
    delta = np.array(delta)
    assert np.all(delta > 0)
    assert delta[-1] < 0.1 * model.fisher_sigma_r(0.0)
    _, exponent, _ = fit_power_law(SIGMAS, delta)
    assert exponent == pytest.approx(2.0, abs=0.05)
    assert exponent == pytest.approx(2.0, abs=0.005)
    k = fit_quadratic(SIGMAS, delta)
    assert np.allclose(delta, k * SIGMAS**2, rtol=0.02)


def test_large_bias_is_not_quadratic(model, noise, ell):
    """Caveat: when delta r >> sigma_r (here the paper's scale, delta r(0.1) ~ 1e-2) the
    68 % point grows faster than sigma^2 (the tensor cosmic variance widens L)."""
    template = np.full(ell.size, 300.0 * noise[2])
    base = model.c_fg_res + noise
    delta = []
    for sigma in SIGMAS:
        sys, nosys = lk.fit_r_common_grid([base + sigma**2 * template, base], model, n=N_GRID)
        delta.append(sys.r_fraction - nosys.r_fraction)
    delta = np.array(delta)
    assert delta[-1] > 10 * model.fisher_sigma_r(0.0)
    local = np.diff(np.log(delta)) / np.diff(np.log(SIGMAS))
    assert local[0] == pytest.approx(2.0, abs=0.01)  # small sigma: still quadratic
    assert local[-1] > 2.1
    _, exponent, _ = fit_power_law(SIGMAS, delta)
    assert exponent > 2.05


def test_r_at_fraction_and_maximum_analytic():
    sigma = 0.3
    grid = lk.r_grid(3.0, 20001)
    half_normal = np.exp(-0.5 * (grid / sigma) ** 2)
    like = half_normal / np.trapezoid(half_normal, grid)
    expected = lk.half_normal_quantile(0.68) * sigma
    assert lk.r_at_fraction(grid, like, 0.68) == pytest.approx(expected, rel=1e-6)
    assert lk.r_at_fraction(grid, like, 0.95) == pytest.approx(1.95996 * sigma, rel=1e-5)
    assert lk.r_maximum_likelihood(grid, like) == 0.0
    centre = 1.23456789e-1  # between grid points
    gauss = np.exp(-0.5 * ((grid - centre) / sigma) ** 2)
    assert lk.r_maximum_likelihood(grid, gauss) == pytest.approx(centre, abs=1e-12)
    cdf = lk.cumulative(grid, like)
    assert cdf[0] == 0.0 and cdf[-1] == 1.0 and np.all(np.diff(cdf) >= 0)


def test_grid_checks(model, noise):
    c_obs = model.c_obs_from_residual(0.01 * model.c_gw_r1 + model.c_fg_res + noise)
    with pytest.raises(ValueError, match="truncates the likelihood"):
        lk.likelihood_curve(lk.r_grid(0.008, 1001), c_obs, model)
    grid = lk.adaptive_r_grid(c_obs, model, n=N_GRID)
    assert grid[0] == 0.0 and grid[-1] > 0.01
    dev = lk.deviance(grid, c_obs, model)
    assert dev[-1] - dev.min() >= lk.DEFAULT_TAIL_DELTA_CHI2
    steps = model.fisher_sigma_r(0.01) / (grid[1] - grid[0])
    assert steps >= lk.MIN_STEPS_PER_SIGMA
    # r_max starts at 6 sigma_r(0) ~ 3e-3 and doubled: the grid for r_in = 0.01 is longer
    grid0 = lk.adaptive_r_grid(model.c_obs_from_residual(model.c_fg_res + noise), model)
    assert grid[-1] > 2 * grid0[-1]


def test_bad_inputs(ell, noise, model):
    with pytest.raises(ValueError, match="lmin"):
        lk.BBModel.from_ptep(F_SKY, lmin=1, lmax=LMAX, n_ell=noise)
    with pytest.raises(ValueError, match="f_sky"):
        lk.BBModel.from_ptep(0.0, lmax=LMAX, n_ell=noise)
    with pytest.raises(ValueError, match="shape"):
        lk.BBModel.from_ptep(F_SKY, lmax=LMAX, n_ell=noise[:-1])
    with pytest.raises(ValueError, match="ell"):
        lk.BBModel(ell=ell[::2], c_lens=1.0, c_gw_r1=1.0, c_fg_res=0.0, n_ell=1.0, f_sky=1.0)
    c_obs = model.c_obs_from_residual(noise)
    c_obs[10] = -1.0
    with pytest.raises(ValueError, match="c_obs must be > 0"):
        lk.minus_two_log_likelihood([0.0, 0.01], c_obs, model)
    with pytest.raises(ValueError, match="r_max"):
        lk.r_grid(0.0)
    with pytest.raises(ValueError, match="fraction"):
        lk.r_at_fraction([0.0, 1.0], [1.0, 1.0], 1.0)


def test_plot_likelihoods(tmp_path, model, noise, ell):
    base = model.c_fg_res + noise
    template = np.full(ell.size, 300.0 * noise[2])
    labels = [sigma_label(0.0)] + [sigma_label(s) for s in SIGMAS]
    spectra = [base] + [base + s**2 * template for s in SIGMAS]
    results = lk.fit_r_common_grid(spectra, model, n=N_GRID)
    grid = results[0].r_grid
    curves = {label: res.likelihood for label, res in zip(labels, results)}
    r68 = {label: res.r_fraction for label, res in zip(labels, results)}
    path = plot_likelihoods(grid, curves, r68, tmp_path / "fig7.png")
    assert path.is_file() and path.stat().st_size > 1000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
