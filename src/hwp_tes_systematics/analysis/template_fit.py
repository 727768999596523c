"""Map-based template fitting: the nonlinearity's known templates fitted to a channel's
a_lm and subtracted, a mitigation the paper leaves for future work.

A systematics channel's a_lm are d = m + sum_k g_k K_k: m the map without the
systematic (CMB, foregrounds, noise), K_k detector k's contamination at g1 = 1 1/K.
What is known of K_k is its seed-independent part, from the fixed pass (the sky the
fixed TOD holds through the s^2, s h and h^2 terms); a seed's own CMB and noise through
the s h term are not (:data:`map_domain.SH_TERM_PIECES`). With the known templates as a
basis B (``basis = "detector"``: one template per detector, the sum of its terms;
``"term"``: each term of each detector, 3 per detector, which absorbs an error on A_2),
the generalised least-squares fit

    beta = G^+ B^T W d,   G = B^T W B,   d' = d - B beta                            (1)

uses the inner product <a, b>_W = sum_{X in T,E,B} sum_{ell=lmin}^{lmax} W^X_ell
[a_l0 b_l0 + 2 sum_{m>0} Re(a_lm^* b_lm)] with W^X_ell = 1 / C^XX_ell of the channel's
map without the systematic (the CMB, noise and foregrounds the templates compete with,
measured on the seed; any weights give an unbiased fit, these a near-optimal one). G^+
is the pseudo-inverse on G's eigenvalues above ``RCOND`` times the largest: two detectors
of one pixel have templates that differ by less than 1e-3 in B, so only their sum is
fitted, and the projection B G^+ B^T W is what the subtraction needs.

Being linear, (1) splits d' = m - P m + sigma (X - P X), P = B G^+ B^T W, X the
contamination at sigma_g1 = 1: the fit removes P m from the sky (its cost, independent of
sigma_g1) and leaves sigma (X - P X) of the systematic (what the templates do not
describe), so the mitigated delta r is again quadratic in sigma_g1. The fit's error on
the coefficients is G^+ B^T W m (sigma_g1 independent), its formal covariance G^+.
"""

from __future__ import annotations

from dataclasses import dataclass

import healpy as hp
import numpy as np

BASES = ("detector", "term")
RCOND = 1e-6  # eigenvalues of G below this times the largest are dropped (degenerate templates)


def check_basis(basis: str) -> str:
    if basis not in BASES:
        raise ValueError(f"mitigation.template_fit = {basis!r}: expected one of {BASES} or null")
    return basis


def mode_weights(lmax: int, lmin: int = 2) -> np.ndarray:
    """(nalm,) 1 for m = 0, 2 for m > 0, 0 below ``lmin``: sum_lm weight Re(a* b) is the
    real inner product of two real fields' a_lm over lmin <= ell <= lmax."""
    ell, m = hp.Alm.getlm(lmax)
    return np.where(ell >= lmin, np.where(m == 0, 1.0, 2.0), 0.0)


def spectrum_weights(cls: np.ndarray, lmax: int, lmin: int = 2) -> np.ndarray:
    """(3, nalm) W^X_ell = 1 / C^XX_ell from ``cls`` (3, lmax + 1) T, E, B auto spectra,
    on each a_lm, times :func:`mode_weights`; 0 where C = 0."""
    cls = np.asarray(cls, dtype=float)[:, : lmax + 1]
    inverse = np.divide(1.0, cls, out=np.zeros_like(cls), where=cls > 0)
    return inverse[:, hp.Alm.getlm(lmax)[0]] * mode_weights(lmax, lmin)


def inverse_spectrum_weights(alm: np.ndarray, lmax: int, lmin: int = 2) -> np.ndarray:
    """:func:`spectrum_weights` of the auto spectra of ``alm`` (3, nalm) as given."""
    return spectrum_weights([hp.alm2cl(a, lmax=lmax) for a in alm], lmax, lmin)


def _inner(a: np.ndarray, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """<a_i, b_j>_W for stacks a (n_a, 3, nalm), b (n_b, 3, nalm): (n_a, n_b)."""
    return np.einsum("isl,jsl->ij", a.real * weights, b.real) + np.einsum(
        "isl,jsl->ij", a.imag * weights, b.imag
    )


@dataclass(frozen=True)
class TemplateFit:
    """The fit (1) of ``basis`` (n_b, 3, nalm) with ``weights`` (3, nalm): G^+ and the
    weighted basis, ready to fit any a_lm of the channel."""

    basis: np.ndarray
    weights: np.ndarray
    gram_pinv: np.ndarray  # G^+ (n_b, n_b)
    rank: int

    @classmethod
    def build(cls, basis: np.ndarray, weights: np.ndarray) -> TemplateFit:
        basis = np.asarray(basis)
        if basis.ndim != 3 or basis.shape[1:] != weights.shape:
            raise ValueError(
                f"template basis of shape {basis.shape}: expected (n, {weights.shape[0]}, "
                f"{weights.shape[1]}) like the weights"
            )
        gram = _inner(basis, basis, weights)
        values, vectors = np.linalg.eigh(gram)
        keep = values > RCOND * max(values.max(), 0.0) if values.size else values > 0
        inverse = np.where(keep, 1.0 / np.where(keep, values, 1.0), 0.0)
        return cls(basis, weights, (vectors * inverse) @ vectors.T, int(keep.sum()))

    def coefficients(self, alm: np.ndarray) -> np.ndarray:
        """beta = G^+ B^T W alm (n_b,) of one (3, nalm) a_lm."""
        return self.gram_pinv @ _inner(self.basis, alm[None], self.weights)[:, 0]

    def fitted(self, alm: np.ndarray) -> np.ndarray:
        """P alm = B beta (3, nalm): the part of ``alm`` the templates describe."""
        return np.tensordot(self.coefficients(alm), self.basis, axes=1)

    def coefficient_errors(self) -> np.ndarray:
        """sqrt(diag G^+): the coefficients' formal errors when W is the inverse covariance
        of what the templates compete with (0 for a direction the fit drops)."""
        return np.sqrt(np.clip(np.diag(self.gram_pinv), 0.0, None))


def channel_basis(term_alms: list[np.ndarray], basis: str) -> np.ndarray:
    """The fit's basis from the known template terms, ``term_alms`` = [c_j T^j_k as
    (n_det, 3, nalm) for j = 0, 1, 2]: per detector their sum (``detector``, n_det rows),
    or every term of every detector (``term``, 3 n_det rows, term-major)."""
    if check_basis(basis) == "detector":
        return sum(term_alms)
    return np.concatenate(term_alms, axis=0)
