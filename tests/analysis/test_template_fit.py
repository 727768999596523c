"""Map-based template fitting (analysis.template_fit) against analytic expectations."""

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.analysis import template_fit as tf

LMAX = 48


def gaussian_alm(rng, amplitude, slope=-1.0):
    """(3, nalm) T, E, B a_lm with C_ell = amplitude (ell + 1)^slope, independent, drawn
    from ``rng`` (hp.synalm draws from numpy's global state, which made the tests depend
    on their order)."""
    ell, m = hp.Alm.getlm(LMAX)
    sd = np.sqrt(amplitude * (ell + 1.0) ** slope)
    shape = (3, ell.size)
    alm = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) * sd / np.sqrt(2.0)
    alm[:, m == 0] = rng.normal(size=(3, int((m == 0).sum()))) * sd[m == 0]
    return alm


def sky_and_templates(rng, n_templates=3):
    sky = gaussian_alm(rng, 1.0)
    templates = np.array([gaussian_alm(rng, 0.01, -2.0) for _ in range(n_templates)])
    return sky, templates


def test_an_injected_g1_is_recovered_within_its_error_and_its_error_is_the_scatter():
    rng = np.random.default_rng(3)
    _, templates = sky_and_templates(rng)
    g1 = np.array([2.0, -1.0, 0.5])
    cl = (np.arange(LMAX + 1) + 1.0) ** -1.0  # the sky's spectrum: W the inverse covariance
    fit = tf.TemplateFit.build(templates, tf.spectrum_weights([cl, cl, cl], LMAX))
    pulls = []
    for _ in range(100):
        sky = gaussian_alm(rng, 1.0)
        beta = fit.coefficients(sky + np.tensordot(g1, templates, axes=1))
        pulls.append((beta - g1) / fit.coefficient_errors())
    pulls = np.array(pulls)
    assert np.all(np.abs(pulls.mean(axis=0)) < 3.5 / np.sqrt(len(pulls)))
    np.testing.assert_allclose(pulls.std(axis=0), 1.0, atol=0.2)


def test_a_template_not_in_the_data_fits_to_zero_within_its_error():
    rng = np.random.default_rng(4)
    sky, templates = sky_and_templates(rng)
    fit = tf.TemplateFit.build(templates, tf.inverse_spectrum_weights(sky, LMAX))
    beta = fit.coefficients(sky + 3.0 * templates[0])
    assert beta[0] == pytest.approx(3.0, abs=4 * fit.coefficient_errors()[0])
    assert np.all(np.abs(beta[1:]) < 4 * fit.coefficient_errors()[1:])


def test_the_fit_removes_the_templates_exactly_and_of_the_sky_only_its_projection():
    """d - P d = m - P m: the contamination goes to rounding, whatever g1, and the sky
    loses only what lies along the templates (a few modes of the thousands)."""
    rng = np.random.default_rng(5)
    sky, templates = sky_and_templates(rng)
    fit = tf.TemplateFit.build(templates, tf.inverse_spectrum_weights(sky, LMAX))
    contamination = np.tensordot([40.0, -7.0, 1e3], templates, axes=1)
    cleaned = sky + contamination - fit.fitted(sky + contamination)
    np.testing.assert_allclose(cleaned, sky - fit.fitted(sky), atol=1e-9 * np.abs(sky).max())
    np.testing.assert_allclose(fit.fitted(contamination), contamination, rtol=1e-9, atol=1e-12)
    removed = hp.alm2cl(fit.fitted(sky)[2]).sum() / hp.alm2cl(sky[2]).sum()
    assert removed < 0.05


def test_degenerate_templates_fit_their_sum():
    """Two detectors of one pixel have (nearly) the same template: the fit keeps one
    direction (rank), and removes any combination of them."""
    rng = np.random.default_rng(6)
    sky, templates = sky_and_templates(rng, 2)
    basis = np.array([templates[0], templates[0], templates[1]])
    fit = tf.TemplateFit.build(basis, tf.inverse_spectrum_weights(sky, LMAX))
    assert fit.rank == 2
    beta = fit.coefficients(sky + 1.5 * basis[0] + 0.5 * basis[1] + basis[2])
    assert beta[0] + beta[1] == pytest.approx(2.0, abs=4 * fit.coefficient_errors()[0])
    data = 1.5 * basis[0] + 0.5 * basis[1]
    np.testing.assert_allclose(fit.fitted(data), data, rtol=1e-9, atol=1e-12)


def test_the_basis_is_per_detector_or_per_term():
    terms = [np.full((2, 3, 5), float(j + 1)) for j in range(3)]
    assert tf.channel_basis(terms, "detector").shape == (2, 3, 5)
    np.testing.assert_array_equal(tf.channel_basis(terms, "detector")[0], 6.0)
    assert tf.channel_basis(terms, "term").shape == (6, 3, 5)
    with pytest.raises(ValueError, match="mitigation.template_fit"):
        tf.channel_basis(terms, "pixel")


def test_the_mitigation_summary_reads_the_seeds():
    """The requirement after the fit from the seeds' mitigated blocks: the Fisher one is
    sqrt(budget / k_mit), the fit's cost its mean and standard error, the recovered g1 the
    slope of response on draws and the rms of the fit's error."""
    from hwp_tes_systematics.analysis.systematic_only import mitigation_summary

    sigma = np.logspace(-5, 0, 21)
    likelihoods = [
        {
            "systematic_only": {
                "mitigated": {
                    "basis": "detector",
                    "k_per_k2": k,
                    "fraction_point_shift": {
                        "sigma_g1_per_k": sigma.tolist(),
                        "delta_r": (k * sigma**2).tolist(),
                    },
                    "fit_cost_delta_r": cost,
                }
            }
        }
        for k, cost in ((1.0, 1e-6), (3.0, 3e-6))
    ]
    fits = [
        {
            "channels": [
                {
                    "channel": "M1-140",
                    "templates_known": "the fixed pass's",
                    "rank": 2,
                    "injected_unit_draw": [1.0, -2.0],
                    "fitted_unit_response": [1.1, -2.2],
                    "fit_error_per_k": [error, -error],
                    "formal_error_per_k": [0.1, 0.1],
                }
            ]
        }
        for error in (0.3, 0.4)
    ]
    summary = mitigation_summary(likelihoods, 6.5e-6, fits)
    assert summary["fisher_peak_shift_requirement_sigma_g1_per_k"] == pytest.approx(
        np.sqrt(6.5e-6 / 2.0)
    )
    assert summary["requirement_sigma_g1_per_k"] == pytest.approx(np.sqrt(6.5e-6 / 2.0), rel=1e-3)
    assert summary["fit_cost_delta_r"] == pytest.approx(2e-6)
    assert summary["fit_cost_delta_r_sem"] == pytest.approx(1e-6)
    channel = summary["per_channel"]["M1-140"]
    assert channel["fitted_over_injected"] == pytest.approx(1.1)
    assert channel["g1_error_rms_per_k"] == pytest.approx(np.sqrt((0.09 + 0.16) / 2))


def _channel(rng, draws, pieces: bool):
    """A systematics channel's a_lm (analysis.channel_alms.ChannelAlms): a sky, three
    template terms per detector, and with ``pieces`` a seed's own part of the s h term
    that the fit does not know."""
    from hwp_tes_systematics.analysis import channel_alms as ca

    n_det = len(draws)
    alms = {"nosys": gaussian_alm(rng, 1.0)}
    for kind in ca.TERM_KINDS:
        alms[kind] = np.array([gaussian_alm(rng, 0.01, -2.0) for _ in range(n_det)])
    if pieces:
        for kind in ca.PIECE_KINDS:
            alms[kind] = np.array([gaussian_alm(rng, 1e-3, -2.0) for _ in range(n_det)])
    detectors = [f"d{i}" for i in range(n_det)]
    return ca.ChannelAlms("M1-140", alms, detectors, 0.01, np.asarray(draws, dtype=float))


def test_the_fit_leaves_of_a_common_g1_what_the_templates_do_not_describe():
    """g1 = 1 on every detector: with templates known whole the fit removes it to
    rounding; with a seed's own s h pieces unknown it leaves X_c - P X_c, orthogonal (in
    the fit's inner product) to every known template, and for unit draws all 1 the same
    as the random population's leftover."""
    rng = np.random.default_rng(11)
    known_whole = _channel(rng, [0.3, -1.2, 0.7], pieces=False)
    whole, _ = known_whole.template_fit("detector", LMAX)
    common = known_whole.detector_templates().sum(axis=0)
    assert np.abs(whole["fit_common_residual"]).max() < 1e-9 * np.abs(common).max()
    channel = _channel(rng, [1.0, 1.0, 1.0], pieces=True)
    left, _ = channel.template_fit("detector", LMAX)
    leftover = left["fit_common_residual"]
    np.testing.assert_allclose(leftover, left["fit_residual"], rtol=1e-12, atol=0)
    known = tf.channel_basis(channel.known_terms(), "detector")
    weights = tf.inverse_spectrum_weights(channel.alms["nosys"], LMAX)
    projections = tf._inner(known, leftover[None], weights)[:, 0]
    scale = np.sqrt(
        tf._inner(known, known, weights).diagonal()
        * tf._inner(leftover[None], leftover[None], weights)[0, 0]
    )
    assert np.all(np.abs(projections) < 1e-9 * scale)
    unknown = sum(channel.alms[kind].sum(axis=0) for kind in ("x1_cmb_h", "x1_noise_h"))
    # X_c = known + unknown: the fit leaves the unknown part less its projection
    expected = unknown - tf.TemplateFit.build(known, weights).fitted(unknown)
    np.testing.assert_allclose(leftover, expected, rtol=0, atol=1e-9 * np.abs(unknown).max())
    norm = tf._inner(np.array([leftover, unknown]), np.array([leftover, unknown]), weights)
    assert 0.5 * norm[1, 1] < norm[0, 0] < norm[1, 1]
