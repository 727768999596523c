"""The detector time constant: a single-pole response, fitted as one nonlinear parameter."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import scipy.fft
import scipy.optimize

from ..fourier import irfft, rfft
from .base import Effect, _value, format_temperature, register


def single_pole(freqs_hz: np.ndarray, tau_s: float) -> np.ndarray:
    """H(f) = 1 / (1 + 2 pi i f tau) (numpy's e^{-2 pi i f t} convention: a phase lag)."""
    return 1.0 / (1.0 + 2j * np.pi * freqs_hz * tau_s)


def single_pole_derivative(freqs_hz: np.ndarray, tau_s: float) -> np.ndarray:
    """dH/dtau = -2 pi i f / (1 + 2 pi i f tau)^2."""
    return -2j * np.pi * freqs_hz / (1.0 + 2j * np.pi * freqs_hz * tau_s) ** 2


@register
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
    discrimination = (
        "a 2f phase error (a nominal adjustment) lags the 2f line only; with only a 2f HWPSS "
        "and a faint sky the two are the SAME signal (the adjustment reports the equivalent "
        "tau = tan(phi) / (2 pi 2 f_HWP)), and the nonlinearity's 4f line lags exactly twice "
        "the 2f line; tau is found from the detector noise's roll-off 1 / (1 + (2 pi f tau)^2) "
        "when the noise passes the pole (photon, phonon noise), or when the lag of other "
        "frequencies is seen (fitted jointly with the 2f phase)"
    )

    # the fit of its one nonlinear parameter (:meth:`.select.FitProblem.fit`): bounds, and the
    # range the linearised start is clipped to
    bounds = (0.0, 1.0)  # s
    # a TES slower than 50 ms would pass 1/sqrt(1 + (2 pi 4 f_HWP tau)^2) < 0.62 of the HFT's
    # 4 f_HWP science band (4.1 Hz): no longer a time constant to correct but a detector out
    # of its operating range; a larger fitted tau is a sky lag, i.e. a pointing offset along
    # the scan (tau ~ offset / 13.8 arcmin/s) (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"tau": 0.05}
    start_range = (1e-7, 0.5)  # s

    noise_signature = "rolloff"

    def fit_noise(self, ctx, residual_f, noise, used, ln_n_eff, **options):
        """The roll-off of each detector's noise as a pole (:func:`.rolloff.fit_rolloff`)."""
        from .rolloff import fit_rolloff

        return fit_rolloff(ctx, residual_f, noise, used, ln_n_eff, **options)

    def noise_entry(self, ctx, fit, noise) -> dict:
        """:meth:`rolloff_entry`."""
        return self.rolloff_entry(ctx, fit)

    def rolloff_evidence(self, ctx, fit) -> str:
        """The noise's roll-off (:class:`.rolloff.RolloffFit`) in words: tau per detector,
        the drop at Nyquist, why the lines cannot show it, what else would do it."""
        taus = ", ".join(
            f"{name}: tau = {1e3 * t:.3g} +- {1e3 * s:.2g} ms ({100 * d:.2g} % lower at Nyquist)"
            for name, t, s, d in zip(
                ctx.detector_names, fit.tau_s, fit.sigma_tau_s, fit.drop_at_nyquist, strict=True
            )
        )
        return (
            f"the detector noise rolls off between {fit.band_hz[0]:g} and {fit.band_hz[1]:.3g} "
            f"Hz as 1 / (1 + (2 pi f tau)^2) ({taus}); the white + 1/f noise alone fits worse "
            f"by Delta chi^2 {-fit.delta_chi2:.0f}. The lines cannot show tau: its lag of the "
            "2f HWPSS, atan(2 pi 2 f_HWP tau), is inside the 2f phase adjustment, and the "
            "nonlinearity's 4f line lags twice as much; a readout or anti-aliasing filter "
            "would roll the noise off as well (not in the catalog)"
        )

    def rolloff_entry(self, ctx, fit) -> dict:
        """The report's entry for a time constant seen in the noise's roll-off."""
        parameters = {
            f"tau[{name}]": {
                "value": float(t),
                "sigma": float(s),
                "unit": "s",
                "detector": name,
                "parameter": "tau",
            }
            for name, t, s in zip(ctx.detector_names, fit.tau_s, fit.sigma_tau_s, strict=True)
        }
        return {
            "name": self.name,
            "title": self.title,
            "parameters": parameters,
            "main_parameters": list(self.main_parameters),
            "delta_chi2": -fit.delta_chi2,  # what leaving it out costs (> 0)
            "delta_bic": fit.delta_bic,
            "evidence": self.rolloff_evidence(ctx, fit),
            "signature": "the detector noise rolls off as 1 / (1 + (2 pi f tau)^2)",
            "look_alikes": [],
        }

    @staticmethod
    def linearised_f(freqs_hz: np.ndarray, d_f: np.ndarray) -> np.ndarray:
        """The first-order change of the spectrum d_f per unit tau: -2 pi i f D(f) (-dd/dt)."""
        return -2j * np.pi * freqs_hz * d_f

    @staticmethod
    def change_f(freqs_hz: np.ndarray, d_f: np.ndarray, tau_s: float, derivative: bool = False):
        """The change of the spectrum d_f: D (H(tau) - 1), or its derivative D dH/dtau."""
        if derivative:
            return d_f * single_pole_derivative(freqs_hz, tau_s)
        return d_f * (single_pole(freqs_hz, tau_s) - 1.0)

    def templates(self, ctx):
        freqs = scipy.fft.rfftfreq(ctx.n_samples, 1.0 / ctx.sampling_rate_hz)
        spectrum = rfft(ctx.d_nom, axis=-1)
        change = self.linearised_f(freqs, spectrum)
        return irfft(change, n=ctx.n_samples, axis=-1)[:, None, :]

    def injection_stage(self, params):
        """With ``through_noise``, on the optical signal and the detector noise together
        (photon and phonon noise pass the TES's pole), before the nonlinearity: the noise
        then rolls off (:mod:`.rolloff`); else on the optical signal alone."""
        return "through_noise" if params.get("through_noise", False) else "signal"

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        tau = _value(params, "tau", tod.shape[0])
        freqs = scipy.fft.rfftfreq(tod.shape[-1], 1.0 / ctx.sampling_rate_hz)
        spectrum = rfft(tod, axis=-1)
        out = np.empty_like(tod)
        for k in range(tod.shape[0]):
            out[k] = irfft(spectrum[k] * single_pole(freqs, tau[k]), n=tod.shape[-1])
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
