"""Effects of the HWP synchronous signal: harmonics other than 2f, intensity coupling
(the 2f modulated by the incoming intensity), the HWP temperature drift and any slow
modulation of the 2f amplitude."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from ..model import Context
from .base import (
    DRIFT_DEGREE,
    HWPSS_HARMONICS,
    INJECTION_HARMONICS,
    MODULATION_MIN,
    NONLINEARITY_HARMONICS,
    SELECTION_THRESHOLD,
    Effect,
    _value,
    format_temperature,
    modulation_degree,
    register,
)
from .gain import _one_relative_drift


def harmonic_templates(ctx: Context, harmonics) -> np.ndarray:
    """cos n(chi - theta), sin n(chi - theta) for each n of ``harmonics``: (n_det, 2 len, n)."""
    angle = ctx.detector_angle
    rows = []
    for n in harmonics:
        rows += [np.cos(n * angle), np.sin(n * angle)]
    return np.stack(rows, axis=1)


@register
class HwpssHarmonics(Effect):
    """HWP synchronous signal left out of the nominal model (which has only A_2 cos 2(chi-theta)).

    sum_n c_n cos n(chi - theta) + s_n sin n(chi - theta), n = 1, 3, 4, 5, 6; the 2f
    amplitude and phase (n = 2) are nominal adjustments (:mod:`.nominal`). The report's
    name for the harmonics found; the selection tries each line on its own
    (:class:`HwpssHarmonic`, two parameters per detector, so a single line is not charged
    for ten) and the report merges the lines it keeps under this name.
    """

    name = "hwpss_harmonics"
    title = "HWP synchronous signal harmonics"
    parameters: ClassVar[dict[str, str]] = {
        f"{cs}{n}": "K" for n in HWPSS_HARMONICS for cs in ("c", "s")
    }
    main_parameters = tuple(parameters)
    selectable = False  # selected line by line: HwpssHarmonic(n)
    signature = "lines at n f_HWP, stationary, with no 2f +- f_spin sidebands"
    discrimination = (
        "NO 2f +- f_spin sidebands (unlike the nonlinearity), constant in time (unlike the "
        "HWP temperature drift), free phase per harmonic (unlike tau)"
    )

    def templates(self, ctx):
        return harmonic_templates(ctx, HWPSS_HARMONICS)

    def apply(self, ctx, params, tod=None):
        """Injection: any harmonic n = 1..6 (c2, s2 too: a 2f error of the simulated HWP)."""
        tod = ctx.d_nom if tod is None else tod
        names = [f"{cs}{n}" for n in INJECTION_HARMONICS for cs in ("c", "s")]
        values = np.stack([_value(params, p, ctx.n_detectors) for p in names], axis=1)
        return tod + np.einsum("kj,kjn->kn", values, harmonic_templates(ctx, INJECTION_HARMONICS))


@register
class HwpssHarmonic(Effect):
    """One line of the HWP synchronous signal: c_n cos n(chi - theta) + s_n sin n(chi - theta).

    A member of ``hwpss_harmonics`` (``reported_as``): selected on its own, reported with
    the other lines found under the family's name.
    """

    signature = HwpssHarmonics.signature
    discrimination = HwpssHarmonics.discrimination
    reported_as = "hwpss_harmonics"

    def __init__(self, n: int):
        self.n = n
        self.name = f"hwpss_harmonic_{n}"
        self.title = f"HWP synchronous signal: the {n} f_HWP line"
        self.parameters = {f"c{n}": "K", f"s{n}": "K"}
        self.main_parameters = (f"c{n}",)

    @classmethod
    def instances(cls) -> tuple[Effect, ...]:
        """One line per harmonic the selection offers (:data:`HWPSS_HARMONICS`)."""
        return tuple(cls(n) for n in HWPSS_HARMONICS)

    def templates(self, ctx):
        return harmonic_templates(ctx, (self.n,))

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        n, parts = self.n, []
        for k, name in enumerate(ev.ctx.detector_names):
            c, s = fit.values[f"c{n}"][k], fit.values[f"s{n}"][k]
            sigma = max(fit.sigmas[f"c{n}"][k], fit.sigmas[f"s{n}"][k])
            amplitude = math.hypot(c, s)
            significance = amplitude / sigma if sigma > 0 else 0.0
            text = (
                f"{name}: a {n} f_HWP line {format_temperature(amplitude)} ({significance:.0f} "
                f"sigma), phase {math.degrees(math.atan2(s, c)):.0f} deg"
            )
            if n in NONLINEARITY_HARMONICS:  # a line a nonlinearity makes too
                (_lo, _, _, lo_sig, *_), (_hi, _, _, hi_sig, *_) = ev.sidebands(k)
                text += (
                    f"; no 2 f_HWP +- f_spin sidebands ({lo_sig:.1f} and {hi_sig:.1f} sigma), "
                    "unlike a nonlinearity"
                )
            parts.append(text)
        return "; ".join(parts)

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        """For the 4f line: a TES nonlinearity, when the nonlinearity that would make the
        line's part in phase with it (g1 A_2^2 / 2 cos(4 (chi - theta) - 2 phi): g1 = 2 a /
        A_2^2 from that part a) predicts 2 f_HWP +- f_spin sidebands g1 A_2 D whose chi^2
        together (both lines, all detectors) could not pay for the nonlinearity in the
        selection (n_det ln N_eff + |Delta BIC threshold|, N_eff ~ n_det n): its only
        signature of its own is then below detection, and a nonlinearity of that size (or
        a part of the line) cannot be excluded, whichever is the larger."""
        if self.n != 4:
            return []
        phases = ev.ctx.hwpss_phase_rad
        snr2 = 0.0
        for k in range(ev.ctx.n_detectors):
            c, s = fit.values["c4"][k], fit.values["s4"][k]
            phi = 0.0 if phases is None else float(phases[k])
            in_phase = c * math.cos(2 * phi) + s * math.sin(2 * phi)
            if not ev.a2[k]:
                continue
            g1 = 2 * in_phase / ev.a2[k] ** 2
            predicted = abs(g1) * ev.a2[k] * ev.dipole_amplitude(k)
            for line in ev.sidebands(k):
                sigma = line[1]
                snr2 += (predicted / sigma) ** 2 if sigma > 0 else 0.0
        n_det = ev.ctx.n_detectors
        detection = n_det * math.log(n_det * ev.ctx.n_samples) + abs(SELECTION_THRESHOLD)
        return ["tes_nonlinearity"] if snr2 < detection else []


def intensity_templates(ctx, n: int) -> np.ndarray:
    """I(t) cos n(chi - theta_k) and I(t) sin n(chi - theta_k), (n_det, 2, n_samples): the
    incoming intensity modulated by the HWP at n f_HWP (the 2f coupling, the 4f leakage)."""
    angle = n * ctx.detector_angle
    return np.stack([ctx.intensity * np.cos(angle), ctx.intensity * np.sin(angle)], axis=1)


@register
class HwpssIntensityCoupling(Effect):
    """Intensity modulated by the HWP (paper's a_n^opt I term): I(t) [a_c cos 2(chi-theta) + a_s sin].

    I(t) = I(p) + D is the intensity seen; the 2f carrier mixes with it into lines at
    2 f_HWP +- (the frequencies of I), mainly 2 f_HWP +- f_spin from the dipole.
    """

    name = "hwpss_intensity_coupling"
    title = "HWP intensity-to-2f coupling"
    parameters: ClassVar[dict[str, str]] = {"a2c": "1", "a2s": "1"}
    # a 2f signal of more than a tenth of the incoming intensity is no HWP's (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"a2c": 0.1, "a2s": 0.1}
    main_parameters = ("a2c",)
    signature_lines = ((2, -1), (2, 1))
    signature = "2 f_HWP +- f_spin sidebands proportional to I (dipole), no 4f line, no DC"
    discrimination = (
        "proportional to I, not to A_2 I; no 4f line, no DC (a nonlinearity making the same "
        "sidebands, g1 = a / (2 A_2), would add a 4f line g1 A_2^2/2)"
    )

    def templates(self, ctx):
        return intensity_templates(ctx, 2)

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        for k, name in enumerate(ev.ctx.detector_names):
            a = math.hypot(fit.values["a2c"][k], fit.values["a2s"][k])
            (lo, _, _, lo_sig, *_), (hi, _, _, hi_sig, *_) = ev.sidebands(k)
            h4 = ev.harmonic(k, 4)
            a2 = ev.a2[k]
            g1_equiv = fit.values["a2c"][k] / (2 * a2) if a2 else math.nan
            parts.append(
                f"{name}: 2 f_HWP - f_spin and 2 f_HWP + f_spin sidebands {format_temperature(lo)} and "
                f"{format_temperature(hi)} ({lo_sig:.1f} and {hi_sig:.1f} sigma), a = {a:.3g} of I; no 4 f_HWP "
                f"line ({format_temperature(h4.amplitude_k)}, {h4.significance_sigma:.1f} sigma) where a "
                f"nonlinearity making the same sidebands (g1 = a/(2 A_2) = {g1_equiv:.3g}/K) "
                f"would give {format_temperature(abs(g1_equiv) * a2**2 / 2)}"
            )
        return "; ".join(parts)


@register
class HwpIntensityLeakage4f(Effect):
    """The HWP's intensity-to-polarisation leakage at 4 f_HWP: I(t) [b_c cos 4(chi-theta) + b_s sin].

    A non-ideal HWP's Mueller elements M_QI, M_UI turn part of the incoming intensity
    into a polarised signal the rotation modulates at 4 f_HWP, the science band (what
    litebird_sim's ``hwp_harmonics`` computes for a non-ideal HWP). I(t) = I(p) + D: the
    dipole makes lines at 4 f_HWP +- f_spin; the mean intensity a 4f line, which a 4f
    HWPSS makes too (the CMB monopole's part, outside I(t), is such a line).
    """

    name = "hwp_intensity_leakage_4f"
    title = "HWP intensity-to-4f leakage (I -> P)"
    parameters: ClassVar[dict[str, str]] = {"b4c": "1", "b4s": "1"}
    # a leakage of more than a tenth of the intensity is no HWP's (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"b4c": 0.1, "b4s": 0.1}
    main_parameters = ("b4c",)
    signature_lines = ((4, -1), (4, 1))
    signature = "4 f_HWP +- f_spin sidebands proportional to I (dipole), in the science band"
    discrimination = (
        "proportional to I at 4 f_HWP: a 4f HWPSS line has no f_spin sidebands, the "
        "nonlinearity and the 2f intensity coupling put theirs at 2 f_HWP +- f_spin, and the "
        "polarised sky's 4f signal does not follow the dipole"
    )

    def templates(self, ctx):
        return intensity_templates(ctx, 4)

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        f4 = 4 * ev.f_hwp
        for k, name in enumerate(ev.ctx.detector_names):
            b = math.hypot(fit.values["b4c"][k], fit.values["b4s"][k])
            lo, _, _, lo_sig, *_ = ev.line(k, f4 - ev.f_spin)
            hi, _, _, hi_sig, *_ = ev.line(k, f4 + ev.f_spin)
            side2 = [ev.line(k, 2 * ev.f_hwp + sign * ev.f_spin)[3] for sign in (-1, 1)]
            parts.append(
                f"{name}: 4 f_HWP - f_spin and 4 f_HWP + f_spin sidebands "
                f"{format_temperature(lo)} and {format_temperature(hi)} ({lo_sig:.1f} and "
                f"{hi_sig:.1f} sigma), b = {b:.3g} of I (the dipole's {format_temperature(b * ev.dipole_amplitude(k))}); "
                f"at 2 f_HWP +- f_spin {side2[0]:.1f} and {side2[1]:.1f} sigma (a nonlinearity "
                "or a 2f coupling would put its sidebands there)"
            )
        return "; ".join(parts)


@register
class HwpTemperatureDrift(Effect):
    """Slow drift of the 2f HWPSS amplitude: A_2,k [sum_{j=1..3} r_j P_j(x)] cos(2 (chi - theta) - phi).

    One HWP: its emission drifts by the same RELATIVE amount r(t) in every detector of a
    channel, so the per-detector amplitudes c_j,k = A_2,k r_j share one set of r_j
    (``shared``). This is what tells it from a gain drift that differs between detectors
    (each TES its own responsivity, as litebird_sim's gain drift draws per detector).
    """

    name = "hwp_temperature_drift"
    title = "HWP temperature drift (2f amplitude drift)"
    parameters: ClassVar[dict[str, str]] = {f"c{j}": "K" for j in range(1, DRIFT_DEGREE + 1)}
    main_parameters = ("c1",)
    signature = (
        "2 f_HWP demodulated amplitude drifting in time by the same relative amount in every "
        "detector; dipole and sky untouched"
    )
    discrimination = (
        "a gain drift that differs between detectors does not fit it, and it costs 3 "
        "parameters where a gain drift costs 3 per detector; dipole and sky untouched (unlike "
        "any gain drift); a gain drift the same in every detector (a common mode) differs "
        "only by the dipole: when the dipole's measured drift cannot exclude it, it is named "
        "as the unresolved look-alike; a constant 2f amplitude error is the nominal "
        "adjustment"
    )
    shared = True

    def shared_scale(self, ctx):
        """s_k = A_2,k: c_j,k = A_2,k r_j."""
        return np.asarray(ctx.a2_k, dtype=float)

    def on_true_hwpss(self, params, a2_true_k, a2_nominal_k, phase_rad):
        """A relative drift of the HWP's emission: c_j [K], given for the nominal A_2,
        scale with each detector's true A_2."""
        relative = np.asarray(a2_true_k, dtype=float) / a2_nominal_k
        return {p: np.asarray(v, dtype=float) * relative for p, v in params.items()}

    def shared_units(self, ctx=None):
        return {f"r{j}": "1" for j in range(1, self.degree(ctx) + 1)}

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        """A gain drift the same in every detector, g_j = r_j, when the dipole's drift it
        would add (2 r_1 / T per hour, relative) is within 3 sigma of the one measured (all
        detectors together): only the dipole tells the two apart, and it does not here."""
        if not self.shared:
            return []
        hours = ev.ctx.duration_s / 3600
        predicted = 2 * fit.shared_values["r1"] / hours
        chi2_gain = chi2_none = 0.0
        for k in range(ev.ctx.n_detectors):
            dipole = ev.drift(k, "dipole_gain")
            sigma = dipole["sigma_per_hour"]
            if not sigma > 0:
                continue
            chi2_gain += ((dipole["slope_per_hour"] - predicted) / sigma) ** 2
            chi2_none += (dipole["slope_per_hour"] / sigma) ** 2
        return ["gain_drift"] if chi2_gain - chi2_none < 9.0 else []

    def degree(self, ctx: Context | None) -> int:
        return DRIFT_DEGREE

    def param_units(self, ctx=None):
        return {f"c{j}": "K" for j in range(1, self.degree(ctx) + 1)}

    def templates(self, ctx):
        carrier = ctx.carrier
        degrees = range(1, self.degree(ctx) + 1)
        return np.stack([ctx.legendre(j)[None, :] * carrier for j in degrees], axis=1)

    def modulation(self, ctx, values: dict) -> np.ndarray:
        """delta A_2(t) per detector [K] for fitted values {c_j: (n_det,)}, (n_det, n)."""
        return sum(
            np.asarray(values[f"c{j}"])[:, None] * ctx.legendre(j)[None, :]
            for j in range(1, self.degree(ctx) + 1)
        )

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        for k, name in enumerate(ev.ctx.detector_names):
            dipole = ev.drift(k, "dipole_gain")
            hwpss = ev.drift(k, "hwpss_2f_cos")
            parts.append(
                f"{name}: the 2f HWPSS amplitude drifts by {format_temperature(hwpss['slope_per_hour'])}/h "
                f"({hwpss['significance_sigma']:.0f} sigma) while the dipole amplitude does not "
                f"({dipole['slope_per_hour'] * 100:.2g} +- {dipole['sigma_per_hour'] * 100:.2g} %/h, "
                f"{dipole['significance_sigma']:.1f} sigma): only the HWP emission changes"
            )
        if self.shared:
            parts.insert(0, _one_relative_drift(fit, "r1", " of A_2", " (one HWP)"))
        return "; ".join(parts)


@register
class HwpssSlowModulation(HwpTemperatureDrift):
    """Slow modulation of the 2f HWPSS amplitude of ANY shape (drift, periodic, smoothed steps).

    delta A_2(t) cos(2 (chi - theta) - phi), delta A_2 = sum_{j=1..D} c_j P_j(x): Legendre
    polynomials up to D = T / 8 min (4..24). A smooth (analytic) modulation converges
    exponentially in this basis once D exceeds ~ e omega / 2 (omega = its phase change over
    half the recording): one period of 1.5 h in 2 h needs D ~ 15, four in 6 h ~ 40; a
    cosine or spline basis of the same size leaves 1e-3 of the amplitude, which a 3 %
    modulation of A_2 turns into lines of several uK. The simple drift (D = 3,
    ``hwp_temperature_drift``) is the nested special case: the selection keeps whichever the
    BIC prefers, the backward step drops the drift when this one is taken.
    """

    name = "hwpss_slow_modulation"
    title = "slow modulation of the 2f HWPSS amplitude (any shape)"
    shared = False  # any shape, per detector: a modulation need not come from the HWP alone
    parameters: ClassVar[dict[str, str]] = {
        f"c{j}": "K" for j in range(1, MODULATION_MIN + 1)
    }  # D grows with the recording's length: see param_units
    signature = (
        "2 f_HWP amplitude changing in time in any smooth way (sidebands within ~D/2T of "
        "2 f_HWP); dipole and sky untouched"
    )
    discrimination = (
        "as hwp_temperature_drift, of which it is the many-parameter generalisation (the BIC "
        "picks one; they are nested)"
    )

    def degree(self, ctx: Context | None) -> int:
        return MODULATION_MIN if ctx is None else modulation_degree(ctx.duration_s)


@register
class HwpEmissionFluctuations(Effect):
    """The HWP's emission fluctuating as a random process (its temperature): A_2 (1 + e(t))
    with e of PSD a^2 (f_ref / f)^beta; the same sidebands of the 2f HWPSS as a gain
    fluctuation (:class:`.gain.GainFluctuations`), without the dipole's. Never fitted on its
    own: named as the look-alike of ``gain_fluctuations`` when the dipole's part of the
    latter is below detection."""

    name = "hwp_emission_fluctuations"
    title = "HWP emission fluctuating in time (a random process)"
    parameters: ClassVar[dict[str, str]] = {"a": "1/sqrt(Hz)", "beta": "1"}
    main_parameters = ("a",)
    kind = "noise"
    selectable = False
    shared = True
    signature = "broadband power in the sidebands of the 2f HWPSS only"
    discrimination = (
        "the dipole and the sky keep their amplitude (a gain fluctuation would modulate them)"
    )
