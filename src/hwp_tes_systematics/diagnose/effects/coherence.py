"""Which detectors share a gain fluctuation: the coherence of the 2f sidebands across three
or more detectors, and the focal-plane groups within which it holds.

The gain g_k(t) = c_G(t) + u_k(t) of detector k in group G: a part common to the group
(a wafer's bath temperature) and a part of its own, with PSDs rho P_g and (1 - rho) P_g
(:mod:`.fluctuations`: P_g = a^2 (f_ref / f)^beta). Per mode, detector k's rfft has the
covariance

    Sigma_G = D + rho (L a a^H + U b b^H),   D_k = S_k + (1 - rho) e_k (L + U),

with S_k its noise, e_k = s_k A_k^2 / 4 its carrier's weight, L = P_g(|f - f_0|),
U = P_g(f + f_0), a_k = sqrt(e_k) e^{i psi_k}, b_k = conj(a_k) (psi_k the carrier's
phase): the two sidebands of one common gain are each rank one. Detectors of different
groups are independent. With W = [a, b], K = rho diag(L, U), G = W^H D^-1 W and
Q = W^H D^-1 C D^-1 W (C the modes' summed cross-periodogram R R^H), Woodbury gives

    ln det Sigma = sum_k ln D_k + ln det(I + K G),
    tr(Sigma^-1 C) = sum_k C_kk / D_k - tr((I + K G)^-1 K Q),

and -2 ln L = 2 sum_bins [n_b ln det Sigma + tr(Sigma^-1 C)] (the Whittle likelihood of
:func:`.fluctuations.fit_fluctuations`, which is this at rho = 0). For a pair it is the pair
likelihood there without the white correlation.

The fit (:func:`fit_coherence`) holds each detector's noise and starts (a, beta) from the
fit of the detectors as independent, then fits (a, beta, rho) for each partition of the
detectors: all in one group, and the groups of each focal-plane key the recording carries
(:attr:`.recording.Recording.groups`). The partition with the highest likelihood is the
fluctuation's scope; its rho says how much of the gain is common.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ..model import Context
from .base import detector_partitions
from .sideband_bins import bin_labels

RHO_STARTS = (0.0, 0.5, 0.9, 1.0)


@dataclass(frozen=True)
class CoherenceFit:
    """The sidebands' coherence within the groups of the best partition of the detectors."""

    by: str  # "all" or the focal-plane key whose groups share a common gain
    groups: dict  # {label: detector indices} of that partition
    correlation: float  # rho: the common part's share of each detector's gain power
    sigma_correlation: float
    amplitude: float  # a and beta refitted with rho
    slope: float
    delta_chi2: float  # -2 ln L at rho against rho = 0 (negative: coherent fits better)
    # -2 ln L of each partition at its best (a, beta, rho): {"all": ..., key: ...}
    partitions: dict


def binned_cross(rows, bins) -> np.ndarray:
    """(n_bins, n_det, n_det) sum over each bin's modes of R R^H; ``bins`` the
    (start, stop) of each bin's contiguous run of modes in ``rows`` (n_det, n_modes)."""
    rows = np.asarray(rows)
    out = np.empty((len(bins), rows.shape[0], rows.shape[0]), dtype=complex)
    for i, (start, stop) in enumerate(bins):
        block = rows[:, start:stop]
        out[i] = block @ block.conj().T
    return out


def contiguous_bins(f, carrier_hz: float):
    """(start, stop) runs of consecutive modes of ``f`` (ascending) in one sideband bin
    (:func:`.sideband_bins.bin_labels`, as the independent fit bins them); each run's mean
    frequency and its modes."""
    key = np.stack(bin_labels(f, carrier_hz))
    starts = np.concatenate([[0], np.flatnonzero(np.any(np.diff(key, axis=1) != 0, axis=0)) + 1])
    stops = np.append(starts[1:], f.size)
    counts = (stops - starts).astype(float)
    mean_f = np.add.reduceat(f, starts) / counts
    return list(zip(starts.tolist(), stops.tolist(), strict=True)), mean_f, counts


def minus_two_ln_l(cross, counts, noise, weights, phases, lower, upper, rho) -> float:
    """-2 ln L of one group (module docstring): ``cross`` (n_b, m, m) the binned
    cross-periodograms, ``counts`` (n_b,) the modes per bin, ``noise`` (m, n_b) S_k,
    ``weights`` (m,) e_k per unit P_g, ``phases`` (m,) psi_k, ``lower``/``upper`` (n_b,)
    P_g at f - f_0 and f + f_0."""
    d = noise + (1 - rho) * weights[:, None] * (lower + upper)  # (m, n_b)
    a = np.sqrt(weights)[:, None] * np.exp(1j * phases)[:, None]  # (m, 1)
    x, y = (a / d).T, (a.conj() / d).T  # D^-1 a, D^-1 b: (n_b, m)
    g_aa = np.sum(weights[:, None] / d, axis=0)
    g_ab = np.sum((weights * np.exp(-2j * phases))[:, None] / d, axis=0)
    q_aa = np.einsum("bi,bij,bj->b", x.conj(), cross, x).real
    q_bb = np.einsum("bi,bij,bj->b", y.conj(), cross, y).real
    q_ab = np.einsum("bi,bij,bj->b", x.conj(), cross, y)
    k_l, k_u = rho * lower, rho * upper
    # A = I + K G = [[1 + kL g_aa, kL g_ab], [kU conj(g_ab), 1 + kU g_aa]]
    det_a = (1 + k_l * g_aa) * (1 + k_u * g_aa) - k_l * k_u * np.abs(g_ab) ** 2
    # tr(A^-1 K Q), A^-1 = adj(A) / det A, K Q = [[kL q_aa, kL q_ab], [kU conj(q_ab), kU q_bb]]
    trace = (
        (1 + k_u * g_aa) * k_l * q_aa
        + (1 + k_l * g_aa) * k_u * q_bb
        - 2 * k_l * k_u * (g_ab * q_ab.conj()).real
    ) / det_a
    diagonal = np.einsum("bii->ib", cross).real
    ln_det = np.sum(np.log(d), axis=0) + np.log(det_a)
    return 2 * float(np.sum(counts * ln_det + np.sum(diagonal / d, axis=0) - trace))


def fit_coherence(
    ctx: Context,
    rows,
    f,
    carrier_hz: float,
    noise,
    weights,
    phases,
    amplitude: float,
    slope: float,
    resolution_hz: float,
    independent: float,
) -> CoherenceFit:
    """The best partition's (a, beta, rho) and rho's error (module docstring). ``rows``:
    the detectors' rfft on the likelihood's modes, at frequencies ``f``; ``noise``: each
    detector's S_k(f) at ``f``; ``weights``: e_k; ``phases``: psi_k; ``amplitude``,
    ``slope``: the independent fit's (a, beta); ``independent``: the gapped
    periodogram's independent modes per mode."""
    from ..curvature import marginal_sigmas
    from .fluctuations import SLOPE_BOUNDS, gain_psd

    bins, mean_f, counts = contiguous_bins(f, carrier_hz)
    starts = np.array([b[0] for b in bins] + [f.size])
    noise_binned = np.stack([np.add.reduceat(s, starts[:-1]) / counts for s in noise])
    cross = binned_cross(rows, bins)
    weights, phases = np.asarray(weights, float), np.asarray(phases, float)
    partitions = detector_partitions(ctx)

    blocks = {  # each partition's groups: their cross-periodograms, S_k, e_k, psi_k
        key: [
            (cross[:, m][:, :, m], noise_binned[m], weights[m], phases[m]) for m in groups.values()
        ]
        for key, groups in partitions.items()
    }
    del cross

    def total(theta, key):
        log_a, beta, rho = theta
        lower = gain_psd(mean_f - carrier_hz, math.exp(log_a), beta, resolution_hz)
        upper = gain_psd(mean_f + carrier_hz, math.exp(log_a), beta, resolution_hz)
        return independent * sum(
            minus_two_ln_l(c, counts, s, e, psi, lower, upper, rho) for c, s, e, psi in blocks[key]
        )

    bounds = [(math.log(1e-9), 0.0), SLOPE_BOUNDS, (0.0, 1.0)]

    def best(key, rhos):
        starts = [np.array([math.log(amplitude), slope, rho]) for rho in rhos]
        start = min(starts, key=lambda x: total(x, key))
        fixed = len(rhos) == 1  # rho held (at 0: the detectors independent)
        result = scipy.optimize.minimize(
            lambda p: total(np.append(p, start[2]) if fixed else p, key),
            start[:2] if fixed else start,
            method="L-BFGS-B",
            bounds=bounds[:2] if fixed else bounds,
        )
        x = np.append(result.x, start[2]) if fixed else result.x
        return x, float(result.fun)

    fits = {key: best(key, RHO_STARTS) for key in partitions}
    by = min(fits, key=lambda key: fits[key][1])
    x, value = fits[by]
    _, independent_value = best(by, (0.0,))
    # marginal errors: rho and a are correlated (a^2 rho sets the cross-spectra, a^2 the
    # detectors' own), so rho's conditional curvature error alone is too small
    sigmas = marginal_sigmas(lambda p: total(p, by), x, steps=(0.02, 0.02, 0.01), bounds=bounds)
    return CoherenceFit(
        by=by,
        groups=partitions[by],
        correlation=float(x[2]),
        sigma_correlation=float(sigmas[2]),
        amplitude=math.exp(x[0]),
        slope=float(x[1]),
        delta_chi2=value - independent_value,
        partitions={key: fit[1] for key, fit in fits.items()},
    )
