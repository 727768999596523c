"""A gain fluctuation shared by three or more detectors (:mod:`.effects.coherence`): the
likelihood of the sidebands' coherence against its dense form and the pair's, and TOAST
recordings whose bath temperature GainDrifter made common to each wafer or to all
detectors, beside a stream of each detector's own."""

from __future__ import annotations

import math

import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.effects.coherence import contiguous_bins, minus_two_ln_l
from hwp_tes_systematics.diagnose.effects.fluctuations import pair_determinant
from hwp_tes_systematics.diagnose.effects.sideband_bins import sum_in_bins
from hwp_tes_systematics.diagnose.recording import read_recording
from hwp_tes_systematics.diagnose.testbed import sky_map

A2_K = 0.2  # the HWPSS amplitude added to TOAST's signal [K_CMB] (assumption, MFT-like)


def _random_group(m: int, seed: int = 1):
    """Binned cross-periodograms of random modes and random model terms for m detectors."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 20, 40).astype(float)
    cross = np.empty((counts.size, m, m), dtype=complex)
    for b, count in enumerate(counts.astype(int)):
        modes = rng.normal(size=(m, count)) + 1j * rng.normal(size=(m, count))
        cross[b] = modes @ modes.conj().T
    noise = rng.uniform(1, 2, (m, counts.size))
    weights, phases = rng.uniform(0.5, 3, m), rng.uniform(0, 2 * np.pi, m)
    lower, upper = rng.uniform(0, 5, counts.size), rng.uniform(0, 1, counts.size)
    return cross, counts, noise, weights, phases, lower, upper


@pytest.mark.parametrize("rho", [0.0, 0.4, 1.0])
def test_the_coherence_likelihood_is_the_dense_one(rho):
    """Woodbury's form equals 2 sum_b [n_b ln det Sigma + tr(Sigma^-1 C)] with Sigma built
    whole: diagonal S_k + e_k (L + U), off-diagonal rho sqrt(e_i e_j) (L e^{i dpsi} + U
    e^{-i dpsi})."""
    cross, counts, noise, weights, phases, lower, upper = _random_group(4)
    a = np.sqrt(weights) * np.exp(1j * phases)
    dense = 0.0
    for b in range(counts.size):
        common = rho * (lower[b] * np.outer(a, a.conj()) + upper[b] * np.outer(a.conj(), a))
        sigma = np.diag(noise[:, b] + weights * (lower[b] + upper[b])) + common
        sigma -= np.diag(np.diag(common))
        dense += 2 * (
            counts[b] * np.log(np.linalg.det(sigma).real)
            + np.trace(np.linalg.solve(sigma, cross[b])).real
        )
    value = minus_two_ln_l(cross, counts, noise, weights, phases, lower, upper, rho)
    assert value == pytest.approx(dense, rel=1e-12)


def test_for_a_pair_it_is_the_pair_likelihood():
    """Two detectors: the pair likelihood of :func:`.fit_fluctuations` (without its white
    correlation), whose determinant is written as a sum of non-negative terms."""
    cross, counts, noise, weights, phases, lower, upper = _random_group(2, seed=2)
    for rho in (0.0, 0.3, 1.0):
        d_psi = phases[0] - phases[1]
        det = pair_determinant(list(noise), list(weights), lower, upper, rho, d_psi)
        c = (
            rho
            * math.sqrt(weights[0] * weights[1])
            * (lower * np.exp(1j * d_psi) + upper * np.exp(-1j * d_psi))
        )
        total = [noise[k] + weights[k] * (lower + upper) for k in range(2)]
        quadratic = (
            total[1] * cross[:, 0, 0].real
            + total[0] * cross[:, 1, 1].real
            - 2 * (c * cross[:, 0, 1].conj()).real
        ) / det
        pair = 2 * np.sum(counts * np.log(det) + quadratic)
        value = minus_two_ln_l(cross, counts, noise, weights, phases, lower, upper, rho)
        assert value == pytest.approx(pair, rel=1e-12)


def test_the_bins_are_those_of_the_independent_fit():
    """The contiguous runs hold the modes :func:`.sideband_bins.sum_in_bins` sums together."""
    f = np.linspace(1e-3, 9.5, 20_000)
    f = f[np.abs(f - 1.3) > 2e-3]
    bins, mean_f, counts = contiguous_bins(f, 1.3)
    reference_f, reference_counts, _, _ = sum_in_bins(f, 1.3, [np.ones_like(f)], None)
    assert sorted(counts) == sorted(reference_counts)
    assert np.allclose(np.sort(mean_f), np.sort(reference_f))
    assert bins[0][0] == 0 and bins[-1][1] == f.size


@pytest.fixture(scope="module")
def sky_fits(tmp_path_factory):
    path = tmp_path_factory.mktemp("sky") / "sky.fits"
    hp.write_map(path, sky_map(), dtype=np.float64)
    return path


@pytest.mark.slow
@pytest.mark.parametrize(
    ("common_to", "sigmas", "seed"),
    [("wafer", (7e-5, 7e-5), 4), ("all", (7e-5, 3e-5), 6)],
)
def test_a_bath_temperature_shared_by_a_wafer_or_all_detectors(
    tmp_path, sky_fits, common_to, sigmas, seed
):
    """TOAST's thermal drift (a 1/f bath temperature up to Nyquist) common to each wafer or
    to all 14 detectors, plus a stream of each detector's own: gain_fluctuations, its scope
    the groups that share the common stream, rho within 3 sigma (or 0.03) of the common
    stream's share of the power."""
    pytest.importorskip("toast", reason="the toast extra is not installed")
    from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

    path = write_toast_recording(
        tmp_path,
        sky_fits,
        hours=1.0,
        seed=seed,
        n_pixels=7,
        wafers=2,
        a2_k=A2_K,
        thermal_drift=sigmas,
        thermal_drift_common_to=common_to,
    )
    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    (entry,) = [e for e in result["effects"] if e["name"] == "gain_fluctuations"]
    assert entry["scope"]["by"] == common_to
    if common_to == "wafer":
        assert sorted(entry["scope"]["groups"]) == ["W0", "W1"]
    rho = entry["parameters"]["rho[common]"]
    expected = sigmas[0] ** 2 / (sigmas[0] ** 2 + sigmas[1] ** 2)
    assert abs(rho["value"] - expected) < max(3 * rho["sigma"], 0.03), (rho, expected)
    assert "the sidebands are coherent" in entry["evidence"]


def test_the_errors_are_marginal_over_correlated_parameters():
    """-2 ln L = (x - mu)^T C^-1 (x - mu): sqrt(C_ii) whatever the correlation, where the
    curvature along one axis gives the conditional sqrt(1 / (C^-1)_ii), 0.44 of it at 0.9."""
    from hwp_tes_systematics.diagnose.curvature import curvature_sigmas, marginal_sigmas

    covariance = np.array(
        [[4e-4, 0.9 * 2e-2 * 3e-2, 0.0], [0.9 * 2e-2 * 3e-2, 9e-4, 0.0], [0, 0, 1e-2]]
    )
    inverse = np.linalg.inv(covariance)
    mu = np.array([0.3, 1.0, 0.5])

    def minus_two_ln_l(x):
        return float((x - mu) @ inverse @ (x - mu))

    bounds = [(-5, 5), (-5, 5), (0.0, 0.505)]  # the last within a step of its bound
    marginal = marginal_sigmas(minus_two_ln_l, mu, (1e-3, 1e-3, 1e-2), bounds)
    assert np.allclose(marginal, np.sqrt(np.diag(covariance)), rtol=1e-6)
    conditional = curvature_sigmas(minus_two_ln_l, mu, (1e-3, 1e-3, 1e-2), bounds)
    assert conditional[0] == pytest.approx(2e-2 * math.sqrt(1 - 0.81), rel=1e-6)
