"""A noise common to a group of detectors (a wafer's bath, a shared bias or readout line,
cosmic rays heating the substrate), told apart from crosstalk by the pattern of the pairs'
correlations.

Detector i's noise n_i = u_i + a_i c(t): its own part and a_i times a noise c common to its
group, white above both knees. Its residual then correlates with every detector j of its
group, and the pairs' normalised cross-spectra (:func:`.crosstalk.fit_crosstalk`, x_ij with
sigma_ij) have the rank-one pattern

    x_ij = b_i b_j (i, j in one group),   0 (different groups),

b_i^2 = a_i^2 P_c / S_i the common part's share of detector i's white noise power. A readout
crosstalk couples chosen pairs, each its own x_ij, with no such pattern. The fit
(:func:`fit_common_mode`): b by weighted least squares on the pairs for each partition of
the detectors (all in one group, the groups of each focal-plane key the recording carries),
the best partition kept; its parameters counted as m per group of m >= 3 detectors and 1
per group of two (a pair gives b_i b_j only). The pairs' correlation beyond b_i b_j is then
tested as crosstalk, pair by pair, and b fitted again without the pairs taken or more
than 4 sigma off the pattern (a coupled pair pulls the b of its two detectors), until
those stay the same; the pattern's chi^2 is then that of the pairs not taken. Against the crosstalk's pairs taken one by one alone, by the BIC: the
better model is taken, and when they come within the selection threshold neither is told
from the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.optimize

from .base import (
    GROUP_KEYS,
    Effect,
    detector_partitions,
    other_partitions,
    partition_scope,
    register,
)


@dataclass
class CommonModeFit:
    """b_i per detector and its error, the partition, and what it gains over no correlation."""

    by: str  # "all" or the focal-plane key of the groups
    groups: dict  # {label: detector indices}
    share: np.ndarray  # b_i (signed: the common noise enters detector i as sign(b_i))
    sigma: np.ndarray
    delta_chi2: float  # chi^2 of the pairs with b_i b_j, less that without (negative)
    n_parameters: int
    delta_bic: float
    partitions: dict  # {key: chi^2 of the pairs at that partition's best b}
    # what crosstalk alone, one x per pair, would take: its pairs and Delta BIC
    pairs_alone: int = 0
    delta_bic_alone: float = 0.0


def rank_one_fit(pairs, coupling, sigma, groups, n_det: int):
    """(b, sigma_b, chi^2) of x_ij = b_i b_j for the pairs within a group, 0 across groups."""
    group_of = np.full(n_det, -1)
    for g, members in enumerate(groups.values()):
        group_of[members] = g
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    coupling, sigma = np.asarray(coupling), np.asarray(sigma)
    inside = group_of[pairs[:, 0]] == group_of[pairs[:, 1]]
    i, j = pairs[inside, 0], pairs[inside, 1]
    x, s = coupling[inside], sigma[inside]
    outside = float(np.sum((coupling[~inside] / sigma[~inside]) ** 2))
    fitted = np.unique(np.concatenate([i, j]))
    if fitted.size == 0:
        return np.zeros(n_det), np.full(n_det, math.inf), outside + float(np.sum((x / s) ** 2))
    start = np.zeros(n_det)
    for k in fitted:  # b_k ~ sqrt(the mean correlation of its pairs)
        mine = (i == k) | (j == k)
        start[k] = math.sqrt(max(float(np.mean(x[mine])), 1e-6))

    def residual(b_fitted):
        b = np.zeros(n_det)
        b[fitted] = b_fitted
        return (x - b[i] * b[j]) / s

    solution = scipy.optimize.least_squares(residual, start[fitted])
    b = np.zeros(n_det)
    b[fitted] = solution.x
    errors = np.full(n_det, math.inf)
    try:
        covariance = np.linalg.pinv(solution.jac.T @ solution.jac)
        errors[fitted] = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    except np.linalg.LinAlgError:
        pass
    return b, errors, outside + float(np.sum(solution.fun**2))


def fit_common_mode(
    ctx, pairs, coupling, sigma, ln_n_eff: float, exclude=None
) -> CommonModeFit | None:
    """The rank-one pattern's best partition (module docstring), on the pairs not in
    ``exclude`` (bool per pair: those a crosstalk of their own takes); None without pairs."""
    if exclude is not None:
        keep = ~np.asarray(exclude, dtype=bool)
        pairs = [p for p, k in zip(pairs, keep, strict=True) if k]
        coupling, sigma = np.asarray(coupling)[keep], np.asarray(sigma)[keep]
    if len(pairs) == 0:
        return None
    n_det = ctx.n_detectors
    partitions = detector_partitions(ctx)
    fits = {
        key: rank_one_fit(pairs, coupling, sigma, groups, n_det)
        for key, groups in partitions.items()
    }
    by = min(fits, key=lambda key: fits[key][2])
    b, errors, chi2 = fits[by]
    none = float(np.sum((coupling / sigma) ** 2))
    n_parameters = sum(len(m) if len(m) >= 3 else 1 for m in partitions[by].values() if len(m) >= 2)
    return CommonModeFit(
        by=by,
        groups=partitions[by],
        share=b,
        sigma=errors,
        delta_chi2=chi2 - none,
        n_parameters=n_parameters,
        delta_bic=chi2 - none + n_parameters * ln_n_eff,
        partitions={key: fit[2] for key, fit in fits.items()},
    )


def common_pattern(pairs, common: CommonModeFit) -> np.ndarray:
    """b_i b_j of each pair within a group of the fit, 0 across groups."""
    label = np.full(common.share.size, -1)
    for g, members in enumerate(common.groups.values()):
        label[members] = g
    return np.array(
        [common.share[i] * common.share[j] if label[i] == label[j] else 0.0 for i, j in pairs]
    )


@register
class CommonModeNoise(Effect):
    """A noise common to a group of detectors: n_i = u_i + a_i c(t), seen as the rank-one
    pattern x_ij = b_i b_j of the pairs' correlations (:func:`fit_common_mode`), fitted with
    the crosstalk (:mod:`.crosstalk`) on the residuals after the selection."""

    name = "common_mode_noise"
    title = "noise common to a group of detectors"
    parameters: ClassVar[dict[str, str]] = {"b": "1"}
    main_parameters = ("b",)
    kind = "noise"
    stage = "noise"
    min_detectors = 2
    signature = (
        "every pair of detectors in a group correlated in the white noise, as x_ij = b_i b_j "
        "(rank one)"
    )
    discrimination = (
        "crosstalk correlates chosen pairs, each by its own x_ij; a common noise every pair of "
        "its group, in a pattern b_i b_j fixed by one share per detector; with two detectors "
        "the two are the same signal"
    )

    def noise_entry(self, ctx, fit, noise) -> dict:
        """The report's entry: b per detector, its scope, the pattern against crosstalk
        (``fit`` a :class:`.crosstalk.CrosstalkFit` whose ``common`` is taken)."""
        common = fit.common
        names = np.asarray(ctx.detector_names)
        parameters = {}
        in_groups = [k for m in common.groups.values() if len(m) >= 2 for k in m]
        for k in sorted(in_groups):
            parameters[f"b[{names[k]}]"] = {
                "value": float(common.share[k]),
                "sigma": float(common.sigma[k]),
                "unit": "1",
                "detector": str(names[k]),
                "parameter": "b",
            }
        nets = [
            abs(common.share[k]) * getattr(noise[k], "net_k_sqrt_s", math.nan) for k in in_groups
        ]
        where = (
            "all detectors"
            if common.by == "all"
            else f"the detectors of each {GROUP_KEYS[common.by]}"
        )
        others = other_partitions(common.partitions, common.by, "one group of all detectors")
        evidence = (
            f"the residuals of {where} are correlated above 1 Hz and above their knee in the "
            f"rank-one pattern x_ij = b_i b_j of one noise they share (b^2, its share of "
            f"each detector's white noise, {np.min(common.share[in_groups] ** 2):.3g} to "
            f"{np.max(common.share[in_groups] ** 2):.3g}: a common noise of "
            f"{1e6 * np.nanmedian(nets):.3g} uK sqrt(s) (median)); Delta chi^2 "
            f"{-common.delta_chi2:.0f} for {common.n_parameters} parameters, where a crosstalk "
            f"per pair takes {common.pairs_alone} pairs for Delta BIC "
            f"{common.delta_bic_alone:.0f}" + (f"; {others}" if others else "")
        )
        return {
            "name": self.name,
            "title": self.title,
            "parameters": parameters,
            "main_parameters": list(self.main_parameters),
            "delta_chi2": -common.delta_chi2,
            "delta_bic": common.delta_bic,
            "evidence": evidence,
            "signature": self.signature,
            "look_alikes": ["detector_crosstalk"] if fit.tied else [],
            "scope": partition_scope(ctx, common.by, common.groups),
        }
