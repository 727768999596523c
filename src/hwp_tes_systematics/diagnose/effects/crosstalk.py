"""Crosstalk between detectors, seen in their noise: a readout that adds c_ij of detector j's
TOD to detector i's, d_i -> d_i + sum_j c_ij d_j.

The signal that leaks is not what shows it. In a co-pointed pair the partner's signal is a
gain, 2f amplitude and polarisation-efficiency change (:class:`.injection_only.Crosstalk`);
between pixels, its dipole is the detector's own to ~1e-3 (a gain), its 2f HWPSS a 2f line
of another phase (the 2f adjustments) and its sky a few uK times c. What the adjustments
cannot take is the partner's NOISE: the residuals of i and j become correlated at every
frequency, with the cross-spectrum

    E[R_i R_j*] = c_ij S_j(f) + c_ji S_i(f),

where uncorrelated detectors have none. Normalised, z_f = Re(R_i R_j*) / sqrt(S_i S_j) has
mean x_ij = c_ij sqrt(S_j / S_i) + c_ji sqrt(S_i / S_j) and variance 1 / 2 per mode. The
fit (:func:`fit_crosstalk`) takes the M modes above 1 Hz, above three times the pair's
higher knee and off the HWP and spin lines (the sky, which both detectors see, and a noise
common to them through a bath or a shared readout below their knee correlate them at low
frequencies only). A gain fluctuating alike in the detectors correlates them too, in the
sidebands of the 2f HWPSS, so z is fitted by least squares as x plus two sideband shapes,
(|f - 2 f_HWP|^-beta + (f + 2 f_HWP)^-beta) / sqrt(S_i S_j) for beta = 1 and 2:

    x_ij = the flat term,   sigma = its marginal error (1 / sqrt(2 M v_ij) without the
    shapes),   Delta chi^2_ij = (x_ij / sigma)^2,

v_ij the fraction of samples valid in both (modes where a fitted fluctuation's sidebands
exceed a tenth of the noise are left out). In the white regime S_j / S_i is a constant, so
the data give x_ij: the leak both ways, c_ij + c_ji for equal noise levels; which way it
goes is not told. A pair is taken when its own Delta BIC = -Delta chi^2 + ln N_eff is below
the selection threshold (5 sigma for a few hours); the effect's Delta BIC is the sum over
the pairs taken, and the report gives the coupling matrix and a bound |x| + 2 sigma for
the pairs not taken.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.fft

from ..model import Context
from ..noise import line_exclusion_mask, periodogram_scale
from .base import SELECTION_THRESHOLD, Effect, register
from .common_mode import CommonModeFit, common_pattern, fit_common_mode

MIN_FREQUENCY_HZ = 1.0  # below it, the sky both detectors see and common 1/f noise
KNEE_FACTOR = 3.0  # the modes used are above this times the pair's higher knee
EXCESS_FRACTION = 0.1  # modes where a fitted gain fluctuation's sidebands exceed this are out
COMMON_PASSES = 4  # the common noise's b and the pairs beyond it, fitted in turn
OUTLIER_SIGMA = 4.0  # a pair this far off the common pattern is left out of its fit


@dataclass
class CrosstalkFit:
    """x_ij per pair of detectors with its sigma, which pairs the BIC takes, the total gain."""

    pairs: list  # (i, j), i < j
    coupling: np.ndarray  # x_ij per pair
    sigma: np.ndarray
    taken: np.ndarray  # bool per pair: Delta BIC below the threshold
    delta_chi2: float  # -sum over the pairs taken of (x / sigma)^2
    delta_bic: float
    # a noise common to groups of detectors, taken before the pairs (then ``coupling`` is
    # each pair's x beyond b_i b_j), or None (:mod:`.common_mode`)
    common: CommonModeFit | None = None
    tied: bool = False  # the two readings within the threshold: not told apart


def fit_crosstalk(ctx: Context, residual_f, noise, ln_n_eff: float, threshold: float):
    """x_ij of every pair from the residuals' rfft ``residual_f`` and their noise models
    ``noise`` (module docstring); ``threshold`` the selection's Delta BIC threshold."""
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    usable = (freqs >= MIN_FREQUENCY_HZ) & (freqs < 0.5 * fs)
    usable &= ~line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * fs / n, 2e-3))
    valid = np.asarray(ctx.valid, dtype=bool)
    carrier = 2 * ctx.f_hwp_hz
    psd = []
    for k, model in enumerate(noise):
        psd.append(periodogram_scale(n, fs, float(valid[k].mean())) * model.psd(freqs))
        excess = getattr(model, "excess_psd", None)
        if excess is not None:  # a fitted gain fluctuation: its sidebands are coherent
            base = model.base.psd(freqs)
            usable &= np.interp(freqs, model.freqs_hz, excess) < EXCESS_FRACTION * base
    pairs, coupling, sigma = [], [], []
    for i in range(ctx.n_detectors):
        for j in range(i + 1, ctx.n_detectors):
            knee = max(getattr(noise[i], "fknee_hz", 0.0), getattr(noise[j], "fknee_hz", 0.0))
            used = usable & (freqs > KNEE_FACTOR * knee)
            m = int(used.sum())
            if m < 100:
                continue
            both = float(np.mean(valid[i] & valid[j]))
            overlap = max(both / math.sqrt(float(valid[i].mean() * valid[j].mean())), 1e-12)
            norm = np.sqrt(psd[i][used] * psd[j][used])
            z = (residual_f[i][used] * residual_f[j][used].conj()).real / norm
            # a gain fluctuation common to the detectors correlates them as its sidebands
            # do, ~|f - 2 f_HWP|^-beta: fitted beside the flat x (beta 1 and 2)
            offset = np.abs(freqs[used] - carrier)
            columns = [np.ones(m)] + [
                (offset**-beta + (freqs[used] + carrier) ** -beta) / norm for beta in (1, 2)
            ]
            design = np.stack([c / np.abs(c).max() for c in columns], axis=1)
            inverse = np.linalg.inv(design.T @ design)  # the normal equations, var(z) = 1/2
            pairs.append((i, j))
            coupling.append(float(inverse[0] @ (design.T @ z)) / overlap)
            sigma.append(math.sqrt(inverse[0, 0] / (2 * max(both, 1e-12))) / overlap)
    coupling, sigma = np.array(coupling), np.array(sigma)
    alone = _pairs_taken(pairs, coupling, sigma, ln_n_eff, threshold)
    outliers = np.zeros(len(pairs), dtype=bool)  # pairs left out of the pattern's fit
    for _ in range(COMMON_PASSES):
        common = fit_common_mode(ctx, pairs, coupling, sigma, ln_n_eff, exclude=outliers)
        if common is None or common.delta_bic >= threshold:
            return alone
        beyond_x = coupling - common_pattern(pairs, common)
        beyond = _pairs_taken(pairs, beyond_x, sigma, ln_n_eff, threshold)
        # a coupled pair pulls the b of its detectors: left out, with those far off it
        now = beyond.taken | (np.abs(beyond_x) > OUTLIER_SIGMA * sigma)
        if np.array_equal(now, outliers):
            break
        outliers = now
    taken = beyond.taken
    # the whole model's Delta BIC over every pair: the pattern where no pair is taken, each
    # pair taken fitted by its own x; the parameters of both. Split between the entries:
    # the pairs', what leaving them out of it costs; the common noise's, the rest.
    misfit = float(np.sum((beyond_x[~taken] / sigma[~taken]) ** 2))
    none = float(np.sum((coupling / sigma) ** 2))
    n_parameters = common.n_parameters + int(taken.sum())
    with_common = misfit - none + n_parameters * ln_n_eff
    common.delta_chi2 = misfit - none - beyond.delta_chi2
    common.delta_bic = with_common - beyond.delta_bic
    if with_common < alone.delta_bic + threshold:  # the common noise, then pairs beyond it
        common.pairs_alone, common.delta_bic_alone = int(alone.taken.sum()), alone.delta_bic
        beyond.common = common
        return beyond
    alone.tied = abs(with_common - alone.delta_bic) < -threshold
    return alone


def _pairs_taken(pairs, coupling, sigma, ln_n_eff: float, threshold: float) -> CrosstalkFit:
    """Each pair taken at its own Delta BIC = -(x / sigma)^2 + ln N_eff."""
    gain = (coupling / sigma) ** 2 if coupling.size else np.zeros(0)
    taken = -gain + ln_n_eff < threshold
    delta_chi2 = -float(gain[taken].sum())
    return CrosstalkFit(
        pairs=pairs,
        coupling=coupling,
        sigma=sigma,
        taken=taken,
        delta_chi2=delta_chi2,
        delta_bic=delta_chi2 + int(taken.sum()) * ln_n_eff if taken.any() else 0.0,
    )


@register
class DetectorCrosstalk(Effect):
    """Crosstalk between detectors: d_i -> d_i + sum_j c_ij d_j, found from the noise it
    correlates (:func:`fit_crosstalk`); x_ij = c_ij + c_ji for equal noise levels."""

    name = "detector_crosstalk"
    title = "crosstalk between detectors"
    parameters: ClassVar[dict[str, str]] = {"x": "1"}
    main_parameters = ("x",)
    kind = "noise"
    stage = "noise"
    min_detectors = 2
    noise_signature = "correlation"
    signature = (
        "the detectors' residuals correlated at every frequency, in proportion to their "
        "noise (a white cross-spectrum where the noise is white)"
    )
    discrimination = (
        "the leaked signal is a gain, 2f and polarisation change the nominal adjustments "
        "take; the sky both see and a common 1/f noise correlate them below 1 Hz and their "
        "knee only, a coherent gain fluctuation near 2 f_HWP only: those modes are left "
        "out; a white noise common to a group (common_mode_noise) correlates every pair of "
        "it as b_i b_j, where crosstalk couples chosen pairs"
    )

    def fit_noise(self, ctx, residual_f, noise, used, ln_n_eff, **options):
        """The coupling of each pair (:func:`fit_crosstalk`; ``options``: ``threshold``)."""
        return fit_crosstalk(
            ctx, residual_f, noise, ln_n_eff, options.get("threshold", SELECTION_THRESHOLD)
        )

    def noise_entry(self, ctx, fit, noise) -> dict:
        """The report's entry: the pairs taken with x and sigma, and the bound on the others."""
        names = ctx.detector_names
        parameters, taken = {}, []
        for (i, j), x, s, keep in zip(fit.pairs, fit.coupling, fit.sigma, fit.taken, strict=True):
            pair = f"{names[i]}-{names[j]}"
            parameters[f"x[{pair}]"] = {
                "value": float(x),
                "sigma": float(s),
                "unit": "1",
                "detector": pair,
                "parameter": "x",
                "taken": bool(keep),  # its own Delta BIC passes the threshold
            }
            if keep:
                taken.append(f"{pair}: x = {x:.3g} +- {s:.2g} ({abs(x) / s:.0f} sigma)")
        others = [
            abs(x) + 2 * s for x, s, keep in zip(fit.coupling, fit.sigma, fit.taken) if not keep
        ]
        bound = f"; the other pairs |x| < {max(others):.2g} (2 sigma)" if others else ""
        beyond = " beyond the common noise's b_i b_j" if fit.common is not None else ""
        evidence = (
            f"the residuals of {len(taken)} of {len(fit.pairs)} pairs are correlated{beyond} above "
            f"1 Hz and above their knee, as a leak of one detector's TOD into the other makes "
            f"({'; '.join(taken)}){bound}; x = c_ij + c_ji for equal noise levels (which way "
            "it leaks is not told: in the white noise the two directions look alike)"
            + (
                "; NOT told apart from common_mode_noise: a noise common to the detectors "
                "(x_ij = b_i b_j) fits within the threshold of the pairs"
                if fit.tied
                else ""
            )
        )
        return {
            "name": self.name,
            "title": self.title,
            "parameters": parameters,
            "main_parameters": list(self.main_parameters),
            "delta_chi2": -fit.delta_chi2,
            "delta_bic": fit.delta_bic,
            "evidence": evidence,
            "signature": self.signature,
            "look_alikes": ["common_mode_noise"] if fit.tied else [],
            "scope": {"by": "pair", "groups": {}},
        }
