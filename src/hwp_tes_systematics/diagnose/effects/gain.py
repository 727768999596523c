"""Gain drifts: per detector, and common to the pair."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from .base import (
    GAIN_DEGREES,
    GROUP_KEYS,
    MODULATION_MIN,
    Effect,
    PerGroup,
    _value,
    detector_partitions,
    group_sentence,
    modulation_degree,
    other_partitions,
    partition_scope,
    register,
)


def _one_relative_drift(fit, param: str, of: str, why: str = "") -> str:
    """The sentence stating a shared drift's common value and what sharing it cost."""
    return (
        f"one relative drift for all detectors{why}: {param} = "
        f"{fit.shared_values[param]:.3g} +- {fit.shared_sigmas[param]:.2g}{of} (sharing it "
        f"costs chi^2 {fit.sharing_chi2:.1f} for {fit.sharing_dof} fewer parameters)"
    )


def smooth_degrees(ctx) -> tuple[int, ...]:
    """1..D, D the slow 2f modulation's degree for this recording (its minimum without one)."""
    top = MODULATION_MIN if ctx is None else modulation_degree(ctx.duration_s)
    return tuple(range(1, top + 1))


def _common_part(g1, sigma, key: str, labels) -> str:
    """A per-detector drift's part common to each group of ``key``: the weighted mean of
    g1 per group and the chi^2 of the detectors about it (per detector beyond it)."""
    labels = np.asarray(labels)
    means, chi2, dof = [], 0.0, 0
    for label in dict.fromkeys(labels):
        members = labels == label
        weights = 1 / sigma[members] ** 2
        mean = float(np.sum(weights * g1[members]) / np.sum(weights))
        means.append(f"{label} {mean:.3g} +- {1 / math.sqrt(float(np.sum(weights))):.2g}")
        chi2 += float(np.sum(weights * (g1[members] - mean) ** 2))
        dof += int(members.sum()) - 1
    return (
        f"g1's part common to each {GROUP_KEYS[key]}: {', '.join(means)}; the detectors "
        f"scatter about it by chi^2 {chi2:.1f} for {dof} degrees of freedom"
        + (" (a part per detector)" if chi2 > dof + 3 * math.sqrt(2 * dof) else " (no more)")
    )


@register
class GainDrift(Effect):
    """Relative gain drift: d_obs = [1 + sum_j g_j P_j(x)] d, j = 1..3 (g0: a nominal adjustment).

    The templates multiply the signal's variations, d - <d>, not its DC level: a detector's
    DC level is mostly a readout offset that the responsivity does not scale, and a drift of
    the DC level cannot be told from the 1/f noise anyway. (With <d> in the template, a gain
    drift of 3e-3 on a 2 mK offset adds a 6 uK ramp that the data do not have, and loses to
    the HWP temperature drift by ~13 in BIC on a recording with a pure gain drift.)
    """

    name = "gain_drift"
    title = "gain error and drift"
    parameters: ClassVar[dict[str, str]] = {f"g{j}": "1" for j in GAIN_DEGREES}
    # a responsivity drifting by more than half of itself in a recording is no drift to
    # correct but a detector out of its operating range (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"g1": 0.5, "g2": 0.5, "g3": 0.5}
    main_parameters = ("g1",)
    signature = "residual proportional to the whole signal (HWPSS and dipole), drifting in time"
    discrimination = (
        "the detectors' relative drifts differ (one HWP drifts them alike: the HWP "
        "temperature drift, shared, cannot follow); it multiplies the dipole and the sky too "
        "(g(t) x dipole, at f_spin in the 1/f noise: a few %/h in 2 hours, ~1 %/h in 6)"
    )

    def degrees(self, ctx) -> tuple[int, ...]:
        """The Legendre degrees j of the drift, P_j(x) over the recording."""
        return GAIN_DEGREES

    def param_units(self, ctx=None) -> dict[str, str]:
        return {f"g{j}": "1" for j in self.degrees(ctx)}

    def templates(self, ctx):
        d = ctx.d_nom
        d = d - np.array([d[k][ctx.valid[k]].mean() for k in range(ctx.n_detectors)])[:, None]
        return np.stack([ctx.legendre(j)[None, :] * d for j in self.degrees(ctx)], axis=1)

    def apply(self, ctx, params, tod=None):
        """Injection: g0 (a constant gain error) is accepted as well as g1..g3."""
        tod = ctx.d_nom if tod is None else tod
        gain = sum(
            _value(params, f"g{j}", tod.shape[0])[:, None] * ctx.legendre(j)[None, :]
            for j in (0, *GAIN_DEGREES)
        )
        return (1.0 + gain) * tod

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        hours = ev.ctx.duration_s / 3600
        for k, name in enumerate(ev.ctx.detector_names):
            dipole = ev.drift(k, "dipole_gain")
            hwpss = ev.drift(k, "hwpss_2f_cos")
            a2 = ev.a2[k]
            rel = hwpss["slope_per_hour"] / a2 if a2 else math.nan
            rel_sigma = hwpss["sigma_per_hour"] / a2 if a2 else math.nan
            g1 = fit.values["g1"][k]
            parts.append(
                f"{name}: the dipole amplitude drifts by {dipole['slope_per_hour'] * 100:.3g} +- "
                f"{dipole['sigma_per_hour'] * 100:.2g} %/h ({dipole['significance_sigma']:.1f} "
                f"sigma) together with the 2f HWPSS ({rel * 100:.3g} +- {rel_sigma * 100:.2g} %/h): "
                f"the whole signal scales, as a gain drift g1 P1 (= {2 * g1 / hours * 100:.3g} %/h) "
                "predicts and an HWP temperature drift (2f only) does not"
            )
        if ev.ctx.n_detectors > 1 and not self.shared:
            g1, sigma = fit.values["g1"], np.maximum(fit.sigmas["g1"], 1e-300)
            mean = np.sum(g1 / sigma**2) / np.sum(1 / sigma**2)
            spread = math.sqrt(float(np.sum(((g1 - mean) / sigma) ** 2)))
            values = ", ".join(f"{v:.3g}" for v in g1)
            parts.append(
                f"the detectors drift differently (g1 = {values}, {spread:.1f} sigma apart): "
                "each TES its own responsivity, where one HWP would move the 2f HWPSS of "
                "every detector by the same relative amount"
                if spread >= 3
                else f"the detectors drift alike (g1 = {values}, {spread:.1f} sigma apart): "
                "the dipole's drift, not the difference between detectors, makes it a gain"
            )
            parts += [_common_part(g1, sigma, key, labels) for key, labels in ev.ctx.groups.items()]
        return "; ".join(parts)


@register
class GainDriftCommon(GainDrift):
    """A gain drift the same in every detector (a common mode, e.g. of the bath temperature).

    The templates of :class:`GainDrift` with one set of g_j for all detectors (``shared``).
    It differs from the HWP temperature drift (also one relative drift for all) only by the
    dipole and sky drifting too, so it carries a prior penalty of 10 in BIC (odds of e^5
    ~ 150 against it): TES responsivities drift by their own amounts (litebird_sim draws
    a slope per detector), one HWP moves every detector's 2f HWPSS alike. It is taken when
    the dipole's drift shows (e.g. 1e-2 in 6 hours), else the HWP temperature drift is, with
    the gain drift named as its unresolved look-alike. Reported as ``gain_drift``.
    """

    name = "gain_drift_common"
    title = "gain drift common to the detectors"
    reported_as = "gain_drift"
    shared = True
    prior_penalty = 10.0
    signature = (
        "residual proportional to the whole signal (HWPSS and dipole), drifting in time by "
        "the same relative amount in every detector"
    )
    discrimination = (
        "the dipole amplitude drifts together with the 2f HWPSS (the same relative drift "
        "in every detector, as one HWP's would be: only the dipole tells them apart)"
    )

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        return _one_relative_drift(fit, "g1", "") + "; " + super().evidence(ev, fit)


@register
class GainDriftPerGroup(PerGroup, GainDriftCommon):
    """A gain drift the same within each focal-plane group and different between groups: a
    wafer's bath temperature, a readout line's bias (``group_by``: one instance per key).

    d_obs = [1 + sum_j g_j P_j(x)] d with one set of g_j per group, j = 1..D and D the
    slow 2f modulation's (:func:`.base.modulation_degree`, one degree per 8 minutes): a
    bath drifts in any smooth way, and the 2f HWPSS measures its shape (a 1/f drift below
    0.2 mHz, TOAST's ``slow_drift``, leaves ~1e-3 of itself beyond P3, which an A_2 of
    0.2 K shows at thousands of sigma; with P1..P3 only, the per-detector
    ``hwpss_slow_modulation`` takes it). With few groups that is still far fewer
    parameters than a modulation per detector; the dipole's drift, with the same shape,
    tells it from an HWP emission modulation. With the prior penalty of
    :class:`GainDriftCommon`: groups that drift alike are also what one HWP's emission
    makes. Offered where the recording's detectors carry the key
    (:attr:`.recording.Recording.groups`). Reported as ``gain_drift``, with its scope.
    """

    signature = (
        "residual proportional to the whole signal (HWPSS and dipole), changing in time in "
        "any smooth way, by the same relative amount in the detectors of one group"
    )
    discrimination = (
        "separate drifts per detector fit no better, one drift for all detectors fits "
        "worse: the detectors of a group drift together"
    )

    group_keys = ("wafer", "squid")
    base_name, base_title = "gain_drift", "gain drift"

    def degrees(self, ctx) -> tuple[int, ...]:
        return smooth_degrees(ctx)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        return group_sentence(self, fit, ("g1",), "") + "; " + GainDrift.evidence(self, ev, fit)


@register
class GainDriftSmooth(GainDrift):
    """A gain drift of any smooth shape, each detector its own: d_obs = [1 + sum_j g_j
    P_j(x)] d, j = 1..D, D the slow 2f modulation's (:func:`.base.modulation_degree`).

    The per-detector form of :class:`GainDriftPerGroup`: a TES whose bath or bias wanders
    (TOAST's ``slow_drift``) drifts beyond P3, and the 2f HWPSS shows it; without this
    form ``hwpss_slow_modulation`` (the same 2f modulation, the dipole untouched) takes it.
    The two have as many parameters and differ by the dipole's and sky's drift alone, so
    this one carries the prior penalty of :class:`GainDriftCommon`: it is taken when the
    dipole's drift shows. Reported as ``gain_drift``.
    """

    name = "gain_drift_smooth"
    title = "gain drift of any smooth shape"
    reported_as = "gain_drift"
    prior_penalty = GainDriftCommon.prior_penalty
    signature = (
        "residual proportional to the whole signal (HWPSS and dipole), changing in time in "
        "any smooth way, each detector its own"
    )
    discrimination = (
        "as hwpss_slow_modulation, with the dipole and the sky changing by the same relative "
        "amount as the 2f HWPSS"
    )

    def degrees(self, ctx) -> tuple[int, ...]:
        return smooth_degrees(ctx)


@register
class GainFluctuations(Effect):
    """A gain fluctuating as a random process, g(t) with PSD P_g(f) = a^2 (f_ref / f)^beta:
    d_obs = (1 + g(t)) d, seen as broadband sidebands of the 2f HWPSS,
    E_k(f) = (A_k^2 / 4) [P_g(|f - 2 f_HWP|) + P_g(f + 2 f_HWP)] (:mod:`.fluctuations`).

    One (a, beta) for all detectors, rho the share of each detector's gain power common to
    its group (1: one focal-plane or wafer temperature; 0: each TES its own), the groups
    (all detectors, or each wafer, readout line or pixel) those that fit best
    (:mod:`.coherence`, three or more detectors; the report's scope); fitted as an excess noise
    by the Whittle likelihood on the residual after the selection, with the detectors'
    noise refitted alongside (``kind`` "noise": :mod:`..select.step` tests it, the linear
    selection never offers it).
    """

    name = "gain_fluctuations"
    title = "gain fluctuating in time (a random process)"
    parameters: ClassVar[dict[str, str]] = {"a": "1/sqrt(Hz)", "beta": "1", "rho": "1"}
    main_parameters = ("a",)
    kind = "noise"
    shared = True
    signature = (
        "broadband power in the sidebands of the 2f HWPSS, falling as a power of the offset "
        "from 2 f_HWP, in proportion to each detector's A_2^2"
    )
    discrimination = (
        "a gain multiplies the dipole and the sky too (their sidebands are ~(D / A_2)^2 ~ "
        "1e-4 of the HWPSS's, in the 1/f noise): usually NOT told apart from an HWP "
        "emission fluctuation; a smooth drift (gain_drift, hwp_temperature_drift) is its "
        "deterministic slow part"
    )

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        return ["hwp_emission_fluctuations"]

    noise_signature = "excess"

    def fit_noise(self, ctx, residual_f, noise, used, ln_n_eff, **options):
        """The Whittle fit of (a, beta, rho) with the noise refitted alongside
        (:func:`.fluctuations.fit_fluctuations`; ``options``: its ``also_from``,
        ``coherence_below``)."""
        from .fluctuations import fit_fluctuations

        return fit_fluctuations(ctx, residual_f, noise, used, ln_n_eff, **options)

    def noise_entry(self, ctx, fit, noise) -> dict:
        """:meth:`report_entry` with what the dipole and sky sidebands would add
        (:func:`.fluctuations.dipole_signature`)."""
        from .fluctuations import dipole_signature

        return self.report_entry(ctx, fit, dipole_signature(ctx, fit, noise))

    def report_entry(self, ctx, fit, dipole_delta_chi2: float) -> dict:
        """The report's entry for the fitted fluctuation (:class:`.fluctuations.FluctuationFit`);
        ``dipole_delta_chi2``: what its dipole and sky sidebands would add
        (:func:`.fluctuations.dipole_signature`), which tells it from an HWP emission one."""
        (look_alike,) = self.unresolved_look_alikes(None, fit)
        dipole = dipole_delta_chi2
        amplitudes = ", ".join(f"{a:.4g} K" for a in fit.carriers_k)
        evidence = (
            f"the 2f HWPSS ({fit.carrier_hz:.4g} Hz) has broadband sidebands, one gain spectrum "
            f"P_g(f) = a^2 (10 mHz / f)^beta for all detectors, a = {fit.amplitude:.3g} +- "
            f"{fit.sigma_amplitude:.2g} /sqrt(Hz), beta = {fit.slope:.3g} +- {fit.sigma_slope:.2g}, "
            f"scaled by each A_2^2 ({amplitudes}); "
            + (
                f"the detectors' sidebands are coherent, rho = {fit.correlation:.3f} +- "
                f"{fit.sigma_correlation:.2g} ("
                + (
                    "one fluctuation for both: a focal-plane or HWP temperature"
                    if fit.correlation > 0.5
                    else "mostly independent: each detector its own"
                )
                + "); "
                if len(fit.carriers_k) == 2
                else ""
            )
            + (coherence_sentence(ctx, fit.coherence) + "; " if fit.coherence else "")
            + f"the gain's rms between 0.1 mHz and f_HWP is "
            f"{fit.rms(1e-4, ctx.f_hwp_hz):.3g}; the noise alone fits worse by Delta chi^2 "
            f"{-fit.delta_chi2:.0f}. A gain would also modulate the dipole and the sky: Delta chi^2 "
            f"~{dipole:.2g} expected from them, "
            + (
                f"below detection: NOT told apart from {look_alike} (the HWP's "
                "emission fluctuating moves the HWPSS alone)"
                if dipole < 25
                else "not fitted apart: read as a gain or an HWP emission fluctuation"
            )
        )
        return {
            "name": self.name,
            "title": self.title,
            "parameters": {
                "a[common]": {
                    "value": fit.amplitude,
                    "sigma": fit.sigma_amplitude,
                    "unit": "1/sqrt(Hz)",
                    "detector": "common",
                    "parameter": "a",
                },
                "beta[common]": {
                    "value": fit.slope,
                    "sigma": fit.sigma_slope,
                    "unit": "1",
                    "detector": "common",
                    "parameter": "beta",
                },
                "rho[common]": {
                    "value": fit.correlation,
                    "sigma": fit.sigma_correlation,
                    "unit": "1",
                    "detector": "common",
                    "parameter": "rho",
                },
            },
            "main_parameters": list(self.main_parameters),
            "delta_chi2": -fit.delta_chi2,  # what leaving it out costs (> 0)
            "delta_bic": fit.delta_bic,
            "evidence": evidence,
            "signature": self.signature,
            "look_alikes": [look_alike],
            "scope": fluctuation_scope(ctx, fit.coherence),
        }


def fluctuation_scope(ctx, coherence) -> dict:
    """The report's scope of a gain fluctuation: the groups within which its common part
    is shared (:class:`.coherence.CoherenceFit`), "all" for a pair or one detector."""
    if coherence is None:
        return partition_scope(ctx, "all", detector_partitions(ctx)["all"])
    return partition_scope(ctx, coherence.by, coherence.groups)


def coherence_sentence(ctx, coherence) -> str:
    """rho and the partition it holds in, against the other partitions, in words."""
    where = (
        "across all detectors"
        if coherence.by == "all"
        else f"within each {GROUP_KEYS[coherence.by]} and independent between them"
    )
    others = other_partitions(
        coherence.partitions, coherence.by, "one common part for all detectors"
    )
    return (
        f"the sidebands are coherent {where}: rho = {coherence.correlation:.3f} +- "
        f"{coherence.sigma_correlation:.2g} of each detector's gain power is common, the "
        f"rest its own (independent detectors fit worse by Delta chi^2 "
        f"{-coherence.delta_chi2:.1f}" + (f"; {others}" if others else "") + ")"
    )
