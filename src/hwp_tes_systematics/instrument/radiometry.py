"""Band-integrated optical power of a single-mode, single-polarisation detector.

A single-mode detector sensitive to one polarisation receives, from a thermal
source of temperature T seen with efficiency eta(nu),

    P = integral eta(nu) w(nu) h nu n(nu, T) d nu,   n = 1 / (exp(h nu / k T) - 1),

where w(nu) is the band transmission (0..1). In the Rayleigh-Jeans limit
h nu << k T this is k T Delta nu eta for a top-hat band of width Delta nu.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.constants import h as H_PLANCK_J_S
from scipy.constants import k as K_BOLTZMANN_J_PER_K

T_CMB_K = 2.72548  # Fixsen 2009, as in the paper
TOP_HAT_SAMPLES = 2001  # frequency samples of a top-hat band (exact edges)


@dataclass(frozen=True)
class Bandpass:
    """Band transmission w(nu) sampled on freqs_ghz (trapezoid integration)."""

    freqs_ghz: np.ndarray
    weights: np.ndarray

    @property
    def effective_width_ghz(self) -> float:
        """integral w(nu) d nu in GHz."""
        return float(np.trapezoid(self.weights, self.freqs_ghz))

    def integrate(self, integrand: np.ndarray) -> float:
        """integral w(nu) f(nu) d nu with nu in Hz, for f sampled on freqs_ghz."""
        return float(np.trapezoid(self.weights * integrand, self.freqs_ghz * 1e9))


def top_hat_bandpass(center_ghz: float, width_ghz: float, samples: int = TOP_HAT_SAMPLES):
    """A top-hat band [center - width/2, center + width/2] with unit transmission."""
    freqs_ghz = np.linspace(center_ghz - width_ghz / 2, center_ghz + width_ghz / 2, samples)
    return Bandpass(freqs_ghz=freqs_ghz, weights=np.ones(samples))


def channel_bandpass(channel) -> Bandpass:
    """The channel's band from the instrument model.

    The PTEP model tabulates its top-hat bands as 0/1 weights on a coarse grid,
    whose trapezoid integral overshoots the nominal width by one grid step; such
    bands are rebuilt as exact top-hats of the nominal centre and width. Any other
    shape is used as tabulated.
    """
    weights = np.asarray(channel.band_weights, dtype=float)
    if np.all((weights == 0.0) | (weights == 1.0)):
        return top_hat_bandpass(channel.bandcenter_ghz, channel.bandwidth_ghz)
    return Bandpass(freqs_ghz=np.asarray(channel.band_freqs_ghz, dtype=float), weights=weights)


def photon_occupation(freq_ghz, temperature_k):
    """Mean photon occupation n = 1 / (exp(h nu / k T) - 1) (dimensionless)."""
    x = H_PLANCK_J_S * np.asarray(freq_ghz) * 1e9 / (K_BOLTZMANN_J_PER_K * temperature_k)
    return 1.0 / np.expm1(x)


def single_mode_spectral_power_w_per_hz(freq_ghz, temperature_k):
    """Power per unit bandwidth of one mode, one polarisation: h nu n(nu, T) [W/Hz]."""
    return H_PLANCK_J_S * np.asarray(freq_ghz) * 1e9 * photon_occupation(freq_ghz, temperature_k)


def band_power_w(bandpass: Bandpass, temperature_k: float, efficiency=1.0) -> float:
    """P = integral eta(nu) w(nu) h nu n(nu, T) d nu [W]; eta scalar or sampled on the band."""
    if temperature_k <= 0:
        raise ValueError(f"temperature_k = {temperature_k}: expected a temperature > 0 K")
    spectral = single_mode_spectral_power_w_per_hz(bandpass.freqs_ghz, temperature_k)
    return bandpass.integrate(np.broadcast_to(efficiency, spectral.shape) * spectral)


def dpower_dtemperature_w_per_k(bandpass: Bandpass, temperature_k: float, efficiency=1.0):
    """Analytic dP/dT = integral eta w k x^2 e^x / (e^x - 1)^2 d nu, x = h nu / k T [W/K]."""
    x = H_PLANCK_J_S * bandpass.freqs_ghz * 1e9 / (K_BOLTZMANN_J_PER_K * temperature_k)
    integrand = K_BOLTZMANN_J_PER_K * x**2 * np.exp(x) / np.expm1(x) ** 2
    return bandpass.integrate(np.broadcast_to(efficiency, integrand.shape) * integrand)


def kelvin_per_watt(
    bandpass: Bandpass,
    efficiency=1.0,
    t_cmb_k: float = T_CMB_K,
    delta_t_k: float = 1e-3,
) -> dict:
    """Power-to-temperature conversion C = delta T / delta P_opt, the paper's four steps.

    1. P_opt(T_CMB); 2. P_opt(T_CMB + delta T); 3. delta P_opt = difference;
    4. C [K/W] = delta T / delta P_opt. ``efficiency`` is the sky-to-detector
    efficiency (scalar or sampled on the band).
    """
    if delta_t_k <= 0:
        raise ValueError(f"delta_t_k = {delta_t_k}: expected a temperature step > 0 K")
    p_nominal_w = band_power_w(bandpass, t_cmb_k, efficiency)
    p_shifted_w = band_power_w(bandpass, t_cmb_k + delta_t_k, efficiency)
    delta_p_w = p_shifted_w - p_nominal_w
    return {
        "p_cmb_w": p_nominal_w,
        "p_cmb_shifted_w": p_shifted_w,
        "delta_p_w": delta_p_w,
        "kelvin_per_watt": delta_t_k / delta_p_w,
    }
