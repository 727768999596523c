"""Catalog of candidate effects: forward models of physics the nominal simulation leaves out.

Every effect acts on the ADJUSTED nominal TOD of each detector k (see :mod:`.model` and
:mod:`.nominal`: gain, 2f HWPSS amplitude and phase, polarisation angle, sky scales,
offsets and noise are fitted on every recording as nuisance parameters, not offered as
effects),

    d_nom = (1 + g)(I(p) + D) + rho (Q cos 2a + U sin 2a) + A_2 cos(2 (chi - theta_k) - phi)
            + ...,

so an effect is only what these adjustments cannot produce: new frequencies, time
dependence, dependence on the incoming intensity, transients.

Each effect has named per-detector parameters with units; a ``shared`` effect has one set
for all detectors, p_k = s_k r (the HWP temperature drift: one HWP), which the fit imposes
exactly on the per-detector solutions (:func:`.linalg.share_across_detectors`) and the
BIC counts once. ``templates(ctx)`` returns T of shape
(n_det, n_param, n) such that, to first order, recording - d_nom = sum_j p_j T_j
(exactly so for the effects whose ``kind`` is "linear"); ``apply(ctx, params, tod)`` is
the full forward model used to inject the effect into a simulated recording (the SAME
equations the diagnosis fits). Legendre polynomials P_j(x) run over the recording,
x = 2 (t - t0) / (t_end - t0) - 1.

Catalog (model and parameters | signature | how it is told apart from look-alikes):

tes_nonlinearity
    model   d + g1 d^2 on the total signal (the paper's quadratic model); g1 [1/K]
    sign.   4 f_HWP line g1 A_2^2/2 WITH a DC shift g1 A_2^2/2 (absorbed by the offset
            adjustment in real data); lines at 2 f_HWP +- f_dipole
            (f_spin) of g1 A_2 D each (HWPSS x dipole), in phase with the 2f HWPSS
    apart   a 4f HWPSS harmonic has no sidebands (and is fitted jointly with it: the shared 4f
            line does not decide, the sidebands and d^2 do); intensity coupling has the
            sidebands but no 4f line and no DC, and a free phase (a_c, a_s: two parameters
            where g1 is one); the sidebands scale as A_2 I (not as I)
tes_nonlinearity_cubic
    model   d + g1 d^2 + g2 d^3; g1 [1/K], g2 [1/K^2] (e.g. an electrothermal TES far from
            its linear range)
    sign.   as tes_nonlinearity, plus a 6 f_HWP line g2 A_2^3/4 and a 2f line 3 g2 A_2^3/4
    apart   tes_nonlinearity is its nested special case (g2 = 0): the BIC keeps the cubic
            term only when its own lines pay for g2 (the backward step drops the other)
detector_time_constant
    model   IFFT[D(f) / (1 + 2 pi i f tau)] (single pole); tau [s]; template -d d_nom/dt
    sign.   phase lag atan(2 pi f tau) growing with frequency: 2f HWPSS, the 4f line of a
            nonlinearity and the sky band together; amplitude factor 1/sqrt(1 + (2 pi f tau)^2)
    apart   a 2f phase error (a nominal adjustment) lags the 2f line only; with only a 2f
            HWPSS and a faint sky the two are the SAME signal (the adjustment reports the
            equivalent tau = tan(phi) / (2 pi 2 f_HWP)); tau is selected only when the lag
            of the other frequencies is seen (fitted jointly with the 2f phase)
hwpss_harmonics (selected line by line: hwpss_harmonic_n, n = 1, 3..6; reported merged)
    model   sum_{n=1,3..6} c_n cos n(chi - theta) + s_n sin n(chi - theta); c_n, s_n [K]
            (n = 2 is the nominal 2f amplitude and phase adjustment, not an effect); each
            line its own candidate with two parameters per detector, so a single line is
            not charged the BIC penalty of ten
    sign.   lines at n f_HWP, stationary
    apart   NO 2f +- f_spin sidebands (unlike the nonlinearity), constant in
            time (unlike the HWP temperature drift), free phase per harmonic (unlike tau)
hwpss_intensity_coupling
    model   I(t) [a_c cos 2(chi - theta) + a_s sin 2(chi - theta)], I = I(p) + D; a_c, a_s [1]
    sign.   sidebands of 2 f_HWP at the frequencies of I: 2 f_HWP +- f_spin (dipole)
    apart   proportional to I, not to A_2 I; no 4f line, no DC (a nonlinearity making the
            same sidebands, g1 = a / (2 A_2), would add a 4f line g1 A_2^2/2)
gain_drift
    model   [sum_{j=1..3} g_j P_j(x)] (d_nom - <d_nom>) (gain drift of the signal, not of the
            readout offset; a constant gain error is a nominal adjustment); g_j [1], one set
            per detector (each TES its own responsivity)
    sign.   residual proportional to the whole signal, changing in time; the dipole amplitude
            drifts together with the 2f HWPSS
    apart   the detectors' relative drifts differ (one HWP drifts them alike: the HWP
            temperature drift, shared, cannot follow); it multiplies the dipole and the sky
            too (g(t) x dipole, at f_spin in the 1/f noise: a few %/h in 2 hours, ~1 %/h in 6)
hwp_temperature_drift
    model   A_2,k [sum_{j=1..3} r_j P_j(x)] cos(2(chi - theta_k) - phi_k); r_j [1] SHARED by
            the detectors (one HWP: its emission drifts by the same relative amount in all);
            reported as c_j,k = A_2,k r_j [K] per detector and r_j [common]
    sign.   2f line broadened (sidebands at ~1/T), 2f demodulated amplitude drifting in time
            by the same relative amount in every detector
    apart   a gain drift that differs between detectors does not fit it, and it costs 3
            parameters where a gain drift costs 3 per detector; dipole and sky untouched
            (unlike any gain drift); a gain drift the same in every detector (a common mode)
            differs only by the dipole: when the dipole's measured drift cannot exclude it,
            it is named as the unresolved look-alike; a constant 2f amplitude error is the
            nominal adjustment
hwpss_slow_modulation
    model   [sum_{j=1..D} c_j P_j(x)] cos(2(chi - theta) - phi), D = T / 8 min (4..24): a
            slow modulation of the 2f amplitude of ANY shape (drift, periodic, smoothed
            steps), not one functional form; c_j [K]
    sign.   2f sidebands within ~D / 2T of 2 f_HWP, demodulated 2f amplitude changing in time
    apart   as hwp_temperature_drift, of which it is the many-parameter generalisation (the
            BIC picks one; they are nested)
glitches
    model   A exp(-(t - t0)/tau_g) for t >= t0 (t0: first hit sample); A [K], t0 [s],
            tau_g [s] per event
    sign.   isolated transients, broadband, uncorrelated with chi and the sky
    apart   found by robust (MAD) thresholding of the whitened residual and fitted per event;
            not periodic in chi, no lines
noise_mismatch (injection only: the white level, knee and slope are nominal adjustments)
    model   P(f) = 2 w^2 (f^a + fk^a)/(f^a + fmin^a): w [K sqrt(s)], fk [Hz], a [1];
            fmin fixed
crosstalk (injection only: not identifiable in a co-pointed orthogonal pair)
    model   d_k + x_k d_nom(other detector); x [1]
    sign.   the other detector's signal: its 2f HWPSS (in antiphase for an orthogonal pair),
            its dipole and sky, its polarisation angle (the 4 chi phase of the other angle)
    apart   in a pair sharing the pointing with orthogonal angles, x d_other = x (I + D) -
            x pol - x A_2 cos 2(chi - theta): exactly a gain, 2f amplitude and polarisation
            efficiency change, i.e. nominal adjustments (A_2 lowered by x A_2, gain raised by
            x); it is therefore not offered as an effect

How each parameter is fitted: jointly with the others, by (weighted) linear least
squares in the whitened Fourier domain for the linear effects; tau by
``scipy.optimize.least_squares`` from the linearised solution (variable projection over
the linear parameters); glitches by detection and a per-event nonlinear fit; the noise
by maximising the Whittle likelihood (see :mod:`.fit` and :mod:`.noise`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.fft
import scipy.optimize

from ..instrument.nonlinearity import apply_nonlinearity
from .model import Context, per_detector

HWPSS_HARMONICS = (1, 3, 4, 5, 6)  # n = 2 is the nominal 2f adjustment
NONLINEARITY_HARMONICS = (4, 6)  # the HWPSS lines d^2 and d^3 make of a 2f HWPSS
INJECTION_HARMONICS = (1, 2, 3, 4, 5, 6)  # a simulated recording may carry any of them
GAIN_DEGREES = (1, 2, 3)  # g0 (a constant gain error) is the nominal gain adjustment
DRIFT_DEGREE = 3  # hwp_temperature_drift: P1..P3
MODULATION_STEP_S = 480.0  # hwpss_slow_modulation: one Legendre degree per 8 minutes
MODULATION_MIN, MODULATION_MAX = 4, 24  # 24: a one-day pair stays within memory and time


def modulation_degree(duration_s: float) -> int:
    """D = T / 8 min, clipped to 4..24: Legendre degrees of the slow 2f modulation."""
    size = math.ceil(duration_s / MODULATION_STEP_S)
    return int(min(max(size, MODULATION_MIN), MODULATION_MAX))


def format_temperature(value_k: float) -> str:
    """A temperature in the most readable unit."""
    magnitude = abs(value_k)
    if magnitude >= 1e-1:
        return f"{value_k:.4g} K"
    if magnitude >= 1e-4:
        return f"{value_k * 1e3:.4g} mK"
    return f"{value_k * 1e6:.3g} uK"


def _value(params: dict, name: str, n_detectors: int) -> np.ndarray:
    return per_detector(params.get(name, 0.0), n_detectors, name)


class Effect:
    """A candidate effect: named per-detector parameters, forward model, signature, evidence.

    One place per effect: its forward model (``apply``), linear templates (``templates``),
    signature and discrimination (texts) and the evidence it states in words on the
    measured residual (``evidence``) live in its class; the fit, the report and the
    simulator only use these.
    """

    name: str = ""
    title: str = ""
    parameters: ClassVar[dict[str, str]] = {}  # parameter -> unit, one value per detector
    main_parameters: tuple[str, ...] = ()
    kind: str = "linear"  # "linear", "nonlinear", "events" or "noise"
    selectable: bool = True  # False: injection only (a nominal adjustment covers it)
    # where it acts: "signal" (on the optical signal, before the detector's response),
    # "response" (the detector's response to the total: the nonlinearity acts on the
    # signal effects too), "noise" or "events" (added after the response)
    stage: str = "signal"
    signature: str = ""
    discrimination: str = ""
    extends: str | None = None  # the simpler catalog effect this one nests (same physics)
    # the report's name for it when it is one member of a family found piece by piece
    # (each line of hwpss_harmonics): the report merges the members it keeps
    reported_as: str | None = None
    # True: one set of parameters for all detectors, p_k = s_k r (``shared_scale``), e.g.
    # one HWP, so one relative drift of its emission; the BIC counts len(parameters) once
    shared: bool = False
    # -2 ln(prior odds) against the effect, added to its BIC (0: none; see GainDriftCommon)
    prior_penalty: float = 0.0

    def shared_scale(self, ctx: Context) -> np.ndarray:
        """s_k of a shared effect, (n_det,): detector k's parameters are s_k times the common ones."""
        return np.ones(ctx.n_detectors)

    def shared_units(self, ctx: Context | None = None) -> dict[str, str]:
        """Common parameter -> unit of a shared effect (default: its own parameters)."""
        return self.param_units(ctx)

    @property
    def family(self) -> str:
        """The physics it names: the effect it nests (``extends``) or is a member of
        (``reported_as``), else itself."""
        return self.extends or self.reported_as or self.name

    def param_units(self, ctx: Context | None = None) -> dict[str, str]:
        """Parameter -> unit for this recording (most effects: the fixed ``parameters``)."""
        return dict(self.parameters)

    def templates(self, ctx: Context) -> np.ndarray | None:
        """T (n_det, n_param, n): recording - d_nom = sum_j p_j T_j to first order."""
        return None

    def apply(self, ctx: Context, params: dict, tod: np.ndarray | None = None) -> np.ndarray:
        """The TOD ``tod`` (default d_nom) with the effect of ``params`` applied."""
        raise NotImplementedError(f"{self.name} has no forward model on a TOD")

    def _linear_apply(self, ctx, params, tod):
        tod = ctx.d_nom if tod is None else tod
        names = self.param_units(ctx)
        values = np.stack([_value(params, p, ctx.n_detectors) for p in names], axis=1)
        return tod + np.einsum("kj,kjn->kn", values, self.templates(ctx))

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        return self.signature

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        """Catalog effects this fit cannot be told from because the signature that would
        tell them apart is below detection in this recording (none by default)."""
        return []

    def __repr__(self) -> str:
        return f"<effect {self.name}>"


class TesNonlinearity(Effect):
    """d_obs = d + g1 d^2 on the total signal (TES gain compression; the paper's model).

    With d = A_2 cos x + D (x = 2 (chi - theta)): g1 d^2 = g1 A_2^2 / 2 (DC) +
    g1 A_2^2 / 2 cos 2x (4 f_HWP) + 2 g1 A_2 D cos x (for D = D0 cos 2 pi f_D t: two lines
    at 2 f_HWP +- f_D of amplitude g1 A_2 D0 each) + g1 D^2.
    """

    name = "tes_nonlinearity"
    title = "TES gain nonlinearity"
    parameters: ClassVar[dict[str, str]] = {"g1": "1/K"}
    powers: ClassVar[tuple[int, ...]] = (2,)  # d_obs - d = sum_j p_j d^powers[j]
    main_parameters = ("g1",)
    stage = "response"
    signature = (
        "4 f_HWP line g1 A_2^2/2 (and a DC shift, inside the offset), 2 f_HWP +- f_spin "
        "sidebands g1 A_2 D each"
    )
    discrimination = "2f +- f_dipole sidebands (g1 A_2 D) accompany the 4f line"

    def response_templates(self, signal: np.ndarray) -> np.ndarray:
        """d^p for each power p of the model, (n_param, n) for one detector's signal d."""
        return np.stack([signal**p for p in self.powers])

    def templates(self, ctx):
        return np.stack([ctx.d_nom**p for p in self.powers], axis=1)

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        n = tod.shape[0]
        unknown = set(params) - set(self.parameters)
        if unknown:
            raise KeyError(
                f"{self.name} has parameters {sorted(self.parameters)}, not {sorted(unknown)}"
                + (" (a cubic term: tes_nonlinearity_cubic)" if "g2" in unknown else "")
            )
        return apply_nonlinearity(tod, _value(params, "g1", n), _value(params, "g2", n))

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        for k, name in enumerate(ev.ctx.detector_names):
            g1 = fit.values["g1"][k]
            g2 = fit.values["g2"][k] if "g2" in fit.values else 0.0
            a2 = ev.a2[k]
            h4 = ev.harmonic(k, 4)
            h6 = ev.harmonic(k, 6)
            valid = ev.ctx.valid[k]
            d = ev.ctx.d_nom[k][valid]
            dc_pred = g1 * float(np.mean(d**2)) + g2 * float(np.mean(d**3))
            (lo, _lo_s, _, lo_sig, *_), (hi, _hi_s, _, hi_sig, *_) = ev.sidebands(k)
            side_pred = abs(g1) * a2 * ev.dipole_amplitude(k)
            text = (
                f"{name}: 4 f_HWP line {format_temperature(h4.amplitude_k)} at {h4.significance_sigma:.1f} sigma "
                f"(predicted g1 A_2^2/2 = {format_temperature(abs(g1) * a2**2 / 2)}); its DC shift "
                f"{format_temperature(dc_pred)} is inside the fitted offset (a nominal adjustment: a detector's "
                "absolute offset is never known); 2 f_HWP - f_spin and "
                f"2 f_HWP + f_spin lines {format_temperature(lo)} and {format_temperature(hi)} at {lo_sig:.1f} and "
                f"{hi_sig:.1f} sigma (predicted g1 A_2 D = {format_temperature(side_pred)} each)"
            )
            if h6 is not None and "g2" in fit.values and abs(fit.sigmas["g2"][k]) > 0:
                text += (
                    f"; 6 f_HWP line {format_temperature(h6.amplitude_k)} at {h6.significance_sigma:.1f} sigma "
                    f"(g2 A_2^3/4 = {format_temperature(abs(g2) * a2**3 / 4)})"
                )
            parts.append(text)
        return "; ".join(parts)

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        """A 4f HWPSS harmonic, when the sidebands g1 A_2 D that the nonlinearity predicts
        are below 3 sigma together (both lines, all detectors): then the nonlinearity rests
        on its 4f line alone, which a 4f harmonic in phase with twice the 2f phase makes too."""
        snr2 = 0.0
        for k in range(len(ev.ctx.detector_names)):
            predicted = abs(fit.values["g1"][k]) * ev.a2[k] * ev.dipole_amplitude(k)
            for line in ev.sidebands(k):
                sigma = line[1]
                snr2 += (predicted / sigma) ** 2 if sigma > 0 else 0.0
        return ["hwpss_harmonics"] if snr2 < 9.0 else []


class TesNonlinearityCubic(TesNonlinearity):
    """d_obs = d + g1 d^2 + g2 d^3: the quadratic model with a cubic term.

    g2 d^3 adds 3 g2 A_2^3 / 4 cos x (2 f_HWP) and g2 A_2^3 / 4 cos 3x (6 f_HWP). The
    quadratic ``tes_nonlinearity`` is its nested special case (g2 = 0): the selection keeps
    whichever the BIC prefers, so g2 is reported only when its lines pay for it.
    """

    name = "tes_nonlinearity_cubic"
    title = "TES gain nonlinearity with a cubic term"
    parameters: ClassVar[dict[str, str]] = {"g1": "1/K", "g2": "1/K^2"}
    powers: ClassVar[tuple[int, ...]] = (2, 3)
    extends = "tes_nonlinearity"
    signature = TesNonlinearity.signature + ", 6 f_HWP line g2 A_2^3/4"
    discrimination = (
        "as tes_nonlinearity; the 6 f_HWP line g2 A_2^3/4 in phase with 3 x the 2f HWPSS"
    )


def single_pole(freqs_hz: np.ndarray, tau_s: float) -> np.ndarray:
    """H(f) = 1 / (1 + 2 pi i f tau) (numpy's e^{-2 pi i f t} convention: a phase lag)."""
    return 1.0 / (1.0 + 2j * np.pi * freqs_hz * tau_s)


def single_pole_derivative(freqs_hz: np.ndarray, tau_s: float) -> np.ndarray:
    """dH/dtau = -2 pi i f / (1 + 2 pi i f tau)^2."""
    return -2j * np.pi * freqs_hz / (1.0 + 2j * np.pi * freqs_hz * tau_s) ** 2


class DetectorTimeConstant(Effect):
    """Single-pole detector response: d_obs = IFFT[D(f) / (1 + 2 pi i f tau)] (circular FFT).

    Linearised, d_obs = d - tau dd/dt: template -d d_nom/dt (spectral derivative). For the
    2f HWPSS the response is a phase lag atan(2 pi 2 f_HWP tau) and an amplitude factor
    1/sqrt(1 + (2 pi 2 f_HWP tau)^2); higher harmonics lag more.
    """

    name = "detector_time_constant"
    title = "detector time constant"
    parameters: ClassVar[dict[str, str]] = {"tau": "s"}
    main_parameters = ("tau",)
    kind = "nonlinear"
    signature = (
        "2 f_HWP residual in quadrature with the HWPSS: phase lag atan(2 pi f tau) and "
        "amplitude loss 1/sqrt(1 + (2 pi f tau)^2), both from one tau"
    )
    discrimination = "one parameter ties phase lag and amplitude loss (a 2f error needs two)"

    def templates(self, ctx):
        freqs = scipy.fft.rfftfreq(ctx.n_samples, 1.0 / ctx.sampling_rate_hz)
        spectrum = scipy.fft.rfft(ctx.d_nom, axis=-1)
        return scipy.fft.irfft(-2j * np.pi * freqs * spectrum, n=ctx.n_samples, axis=-1)[:, None, :]

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        tau = _value(params, "tau", tod.shape[0])
        freqs = scipy.fft.rfftfreq(tod.shape[-1], 1.0 / ctx.sampling_rate_hz)
        spectrum = scipy.fft.rfft(tod, axis=-1)
        out = np.empty_like(tod)
        for k in range(tod.shape[0]):
            out[k] = scipy.fft.irfft(spectrum[k] * single_pole(freqs, tau[k]), n=tod.shape[-1])
        return out

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        omega = 2 * np.pi * 2 * ev.f_hwp
        for k, name in enumerate(ev.ctx.detector_names):
            tau = fit.values["tau"][k]
            static = ev.drift(k, "static")
            a2 = ev.a2[k]
            c, s = static["hwpss_2f_cos_k"], static["hwpss_2f_sin_k"]
            s_sigma = static["hwpss_2f_sin_sigma_k"]
            lag = math.atan2(s, a2 + c)
            factor = math.hypot(a2 + c, s) / a2 if a2 else math.nan
            lag_pred = math.atan(omega * tau)
            factor_pred = 1 / math.sqrt(1 + (omega * tau) ** 2)
            parts.append(
                f"{name}: the 2 f_HWP HWPSS has a quadrature residual {format_temperature(s)} at "
                f"{abs(s) / s_sigma if s_sigma else 0:.0f} sigma, i.e. it lags by "
                f"{lag * 1e3:.3f} mrad with amplitude factor {factor:.6f}; one tau = "
                f"{tau * 1e3:.4g} ms predicts a lag atan(2 pi 2f_HWP tau) = {lag_pred * 1e3:.3f} "
                f"mrad and a factor 1/sqrt(1+(2 pi 2f_HWP tau)^2) = {factor_pred:.6f}"
            )
        return "; ".join(parts)


def harmonic_templates(ctx: Context, harmonics) -> np.ndarray:
    """cos n(chi - theta), sin n(chi - theta) for each n of ``harmonics``: (n_det, 2 len, n)."""
    angle = ctx.detector_angle
    rows = []
    for n in harmonics:
        rows += [np.cos(n * angle), np.sin(n * angle)]
    return np.stack(rows, axis=1)


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
    discrimination = "no 2f +- f_spin sidebands, constant in time"

    def templates(self, ctx):
        return harmonic_templates(ctx, HWPSS_HARMONICS)

    def apply(self, ctx, params, tod=None):
        """Injection: any harmonic n = 1..6 (c2, s2 too: a 2f error of the simulated HWP)."""
        tod = ctx.d_nom if tod is None else tod
        names = [f"{cs}{n}" for n in INJECTION_HARMONICS for cs in ("c", "s")]
        values = np.stack([_value(params, p, ctx.n_detectors) for p in names], axis=1)
        return tod + np.einsum("kj,kjn->kn", values, harmonic_templates(ctx, INJECTION_HARMONICS))


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


class HwpssIntensityCoupling(Effect):
    """Intensity modulated by the HWP (paper's a_n^opt I term): I(t) [a_c cos 2(chi-theta) + a_s sin].

    I(t) = I(p) + D is the intensity seen; the 2f carrier mixes with it into lines at
    2 f_HWP +- (the frequencies of I), mainly 2 f_HWP +- f_spin from the dipole.
    """

    name = "hwpss_intensity_coupling"
    title = "HWP intensity-to-2f coupling"
    parameters: ClassVar[dict[str, str]] = {"a2c": "1", "a2s": "1"}
    main_parameters = ("a2c",)
    signature = "2 f_HWP +- f_spin sidebands proportional to I (dipole), no 4f line, no DC"
    discrimination = "sidebands scale with I, not with A_2 I; no 4f line"

    def templates(self, ctx):
        angle = 2 * ctx.detector_angle
        return np.stack([ctx.intensity * np.cos(angle), ctx.intensity * np.sin(angle)], axis=1)

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


def _one_relative_drift(fit, param: str, of: str, why: str = "") -> str:
    """The sentence stating a shared drift's common value and what sharing it cost."""
    return (
        f"one relative drift for all detectors{why}: {param} = "
        f"{fit.shared_values[param]:.3g} +- {fit.shared_sigmas[param]:.2g}{of} (sharing it "
        f"costs chi^2 {fit.sharing_chi2:.1f} for {fit.sharing_dof} fewer parameters)"
    )


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
    main_parameters = ("g1",)
    signature = "residual proportional to the whole signal (HWPSS and dipole), drifting in time"
    discrimination = "the dipole amplitude drifts together with the 2f HWPSS"

    def templates(self, ctx):
        d = ctx.d_nom
        d = d - np.array([d[k][ctx.valid[k]].mean() for k in range(ctx.n_detectors)])[:, None]
        return np.stack([ctx.legendre(j)[None, :] * d for j in GAIN_DEGREES], axis=1)

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
        return "; ".join(parts)


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
        "only the 2f HWPSS moves, the dipole does not; one relative drift for all detectors "
        "(one HWP), where a gain drift may differ from detector to detector"
    )
    shared = True

    def shared_scale(self, ctx):
        """s_k = A_2,k: c_j,k = A_2,k r_j."""
        return np.asarray(ctx.a2_k, dtype=float)

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
    discrimination = "only the 2f HWPSS moves, the dipole does not; any shape, not a drift"

    def degree(self, ctx: Context | None) -> int:
        return MODULATION_MIN if ctx is None else modulation_degree(ctx.duration_s)


@dataclass(frozen=True)
class GlitchEvent:
    """A cosmic-ray hit: A exp(-(t - t0)/tau) for t >= t0 (t0 = the first affected sample)."""

    detector: int
    time_s: float
    amplitude_k: float
    tau_s: float
    sigma_amplitude_k: float = 0.0
    sigma_tau_s: float = 0.0
    significance: float = 0.0


GLITCH_TAIL_CUT = 25.0  # the exponential tail is evaluated over 25 tau


def glitch_profile(times_s: np.ndarray, time_s: float, amplitude_k: float, tau_s: float):
    """(first index, values) of one event: A exp(-(t - t0)/tau) at samples t >= t0."""
    first = int(np.searchsorted(times_s, time_s - 1e-9))
    dt = times_s[1] - times_s[0] if times_s.size > 1 else 1.0
    length = max(1, int(np.ceil(GLITCH_TAIL_CUT * max(tau_s, 1e-6) / dt)) + 1)
    stop = min(times_s.size, first + length)
    values = amplitude_k * np.exp(-(times_s[first:stop] - time_s) / max(tau_s, 1e-9))
    return first, values


def glitch_tod(times_s: np.ndarray, n_detectors: int, events) -> np.ndarray:
    """Sum of the events' exponential tails, (n_det, n)."""
    out = np.zeros((n_detectors, times_s.size))
    for event in events:
        first, values = glitch_profile(times_s, event.time_s, event.amplitude_k, event.tau_s)
        out[event.detector, first : first + values.size] += values
    return out


def fit_glitch(
    residual: np.ndarray,
    times_s: np.ndarray,
    index: int,
    sigma_k: float,
    detector: int,
    tau_guess_s: float,
    window_s: float = 4.0,
) -> GlitchEvent | None:
    """Nonlinear least-squares fit of one event at sample ``index`` (the first hit sample).

    Model on a window around the event: c + A exp(-(t - t0)/tau) (t >= t0), with c a local
    offset (1/f noise, slow signals); ``scipy.optimize.least_squares`` over (c, A, ln tau);
    uncertainties from the Jacobian with the white noise ``sigma_k`` per sample.
    """
    dt = times_s[1] - times_s[0]
    half = max(8, int(window_s / dt))
    lo, hi = max(0, index - half // 4), min(times_s.size, index + half)
    t = times_s[lo:hi]
    y = residual[lo:hi]
    t0 = times_s[index]
    after = t >= t0 - 1e-9

    def model(theta):
        c, amplitude, log_tau = theta
        out = np.full_like(t, c)
        out[after] += amplitude * np.exp(-(t[after] - t0) / np.exp(log_tau))
        return out

    def fun(theta):
        return (model(theta) - y) / sigma_k

    start = np.array(
        [np.median(y[~after]) if np.any(~after) else 0.0, y[after][0], np.log(tau_guess_s)]
    )
    start[1] -= start[0]
    try:
        solution = scipy.optimize.least_squares(
            fun,
            start,
            bounds=([-np.inf, -np.inf, np.log(0.05 * dt)], [np.inf, np.inf, np.log(5.0)]),
        )
    except ValueError:
        return None
    jac = solution.jac
    try:
        cov = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return None
    _c, amplitude, log_tau = solution.x
    tau = float(np.exp(log_tau))
    sigma_amplitude = float(np.sqrt(max(cov[1, 1], 0.0)))
    sigma_tau = float(tau * np.sqrt(max(cov[2, 2], 0.0)))
    return GlitchEvent(
        detector=detector,
        time_s=float(t0),
        amplitude_k=float(amplitude),
        tau_s=tau,
        sigma_amplitude_k=sigma_amplitude,
        sigma_tau_s=sigma_tau,
        significance=float(abs(amplitude) / sigma_amplitude) if sigma_amplitude > 0 else 0.0,
    )


class Glitches(Effect):
    """Cosmic-ray glitches: sum_i A_i exp(-(t - t_i)/tau_i) for t >= t_i.

    t_i is the first affected sample (a hit between two samples is the same model with A
    scaled by exp(-delta/tau)). Detection: samples of the whitened residual above a robust
    threshold (median absolute deviation), then a nonlinear fit per event (:func:`fit_glitch`).
    """

    name = "glitches"
    title = "cosmic-ray glitches"
    parameters: ClassVar[dict[str, str]] = {"amplitude": "K", "time": "s", "tau": "s"}
    main_parameters = ("amplitude",)
    kind = "events"
    stage = "events"
    signature = "isolated transients in time, uncorrelated with chi and the sky"
    discrimination = "not periodic in chi, no lines, localised in time"

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        events = params.get("events", [])
        events = [e if isinstance(e, GlitchEvent) else GlitchEvent(*e) for e in events]
        return tod + glitch_tod(ctx.times_s, tod.shape[0], events)

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        events = fit.events
        if not events:
            return "no transient left after the fit"
        strongest = max(events, key=lambda e: e.significance)
        taus = np.array([e.tau_s for e in events])
        names = ev.ctx.detector_names
        per_det = {name: sum(e.detector == k for e in events) for k, name in enumerate(names)}
        counts = ", ".join(f"{n} in {name}" for name, n in per_det.items())
        return (
            f"{len(events)} isolated transients ({counts}); the strongest "
            f"{format_temperature(strongest.amplitude_k)} at t = {strongest.time_s:.2f} s ({strongest.significance:.0f} "
            f"sigma) in {names[strongest.detector]}; exponential tails tau = "
            f"{np.median(taus) * 1e3:.0f} ms (median); localised in time, not periodic in chi"
        )


class NoiseMismatch(Effect):
    """Noise unlike the configured one: P(f) = 2 w^2 (f^a + fk^a) / (f^a + fmin^a), one-sided.

    w = NET [K sqrt(s)] (white level, sigma per sample = w sqrt(f_s)), fk the knee, a the
    slope, fmin fixed at the configured value (litebird_sim's "toast" model).
    """

    name = "noise_mismatch"
    title = "noise unlike the configured NET / f_knee / alpha"
    parameters: ClassVar[dict[str, str]] = {"net": "K sqrt(s)", "fknee": "Hz", "alpha": "1"}
    main_parameters = ("net",)
    kind = "noise"
    stage = "noise"
    selectable = False  # the white level, knee and slope are nominal adjustments
    signature = "excess broadband power, no lines"
    discrimination = "smooth power spectrum change, explained by no template"


class Crosstalk(Effect):
    """A fraction x of the other detector's signal: d_obs,k = d_k + x_k d_other(k)."""

    name = "crosstalk"
    title = "crosstalk from the other detector of the pair"
    parameters: ClassVar[dict[str, str]] = {"x": "1"}
    main_parameters = ("x",)
    selectable = False  # gain + A_2 + polarisation-efficiency adjustments in a pair
    signature = "the other detector's signal: its (antiphase) 2f HWPSS, dipole and polarisation"
    discrimination = "2f HWPSS changes by -x A_2 while the dipole changes by +x D"

    def templates(self, ctx):
        return ctx.other[:, None, :]

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        x = _value(params, "x", tod.shape[0])
        return tod + x[:, None] * tod[ctx.partner]

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        parts = []
        for k, name in enumerate(ev.ctx.detector_names):
            static = ev.drift(k, "static")
            x = fit.values["x"][k]
            a2 = ev.a2[k]
            c = static["hwpss_2f_cos_k"]
            g = static["dipole_gain"]
            parts.append(
                f"{name}: the 2f HWPSS changes by {c / a2 if a2 else math.nan:+.3g} of A_2 while "
                f"the dipole changes by {g:+.3g} +- {static['dipole_gain_sigma']:.2g} of itself: "
                f"opposite signs, as the other (orthogonal) detector's signal with x = {x:.4g} "
                "gives (its HWPSS is in antiphase, its dipole in phase)"
            )
        return "; ".join(parts)


CATALOG: dict[str, Effect] = {
    effect.name: effect
    for effect in (
        TesNonlinearity(),
        TesNonlinearityCubic(),
        DetectorTimeConstant(),
        HwpssHarmonics(),
        *(HwpssHarmonic(n) for n in HWPSS_HARMONICS),
        HwpssIntensityCoupling(),
        GainDrift(),
        GainDriftCommon(),
        HwpTemperatureDrift(),
        HwpssSlowModulation(),
        Glitches(),
        NoiseMismatch(),
        Crosstalk(),
    )
}


# Effects on the signal, which the detector nonlinearity then acts on (they come before it).
SIGNAL_EFFECTS = frozenset(name for name, e in CATALOG.items() if e.stage == "signal")
RESPONSE_STAGE = frozenset(name for name, e in CATALOG.items() if e.stage == "response")


def reported_name(name: str) -> str:
    """The name the report gives an effect: its family's for a member (``reported_as``)."""
    return CATALOG[name].reported_as or name if name in CATALOG else name


def family_of(name: str) -> str:
    """The physics a name reports (:attr:`Effect.family`); a name outside the catalog (an
    injection-only effect) is its own family."""
    return CATALOG[name].family if name in CATALOG else name


def get_effect(name: str) -> Effect:
    try:
        return CATALOG[name]
    except KeyError:
        raise KeyError(f"unknown effect {name!r}; the catalog has {sorted(CATALOG)}") from None


def catalog_table() -> list[dict]:
    """One row per effect: name, parameters with units, signature, discrimination."""
    return [
        {
            "name": e.name,
            "title": e.title,
            "parameters": dict(e.parameters),
            "signature": e.signature,
            "discrimination": e.discrimination,
        }
        for e in CATALOG.values()
    ]
