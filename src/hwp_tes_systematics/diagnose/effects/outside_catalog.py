"""Effects OUTSIDE the catalog (``role = "outside"``): simulated recordings may carry them,
the diagnosis has no model of them and must leave them in ``unexplained``; signal effects,
injected with the catalog's signal effects before the noise."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..model import per_detector
from .base import Effect, register


@register
class HwpssSineModulation(Effect):
    """A_2 [1 + m sin(2 pi t / P + phi)] cos(2 (chi - theta) - phi_2): a periodic 2f modulation.

    Modulates the recording's actual HWPSS: ``a2_k`` and ``hwpss_phase_rad`` (phi_2), when
    given, are its true amplitude and phase (default: the nominal ones).
    """

    name = "hwpss_sine_modulation"
    title = "periodic modulation of the 2f HWPSS"
    parameters: ClassVar[dict[str, str]] = {"relative": "1", "period_s": "s", "phase_rad": "rad"}
    main_parameters = ("relative",)
    role = "outside"
    selectable = False
    signature = "sidebands of the 2f HWPSS at 2 f_HWP +- 1 / P"
    discrimination = "a line pair no catalog effect makes (a slow drift has no period)"

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        relative = per_detector(params["relative"], ctx.n_detectors, "relative")
        a2 = per_detector(params.get("a2_k", ctx.a2_k), ctx.n_detectors, "a2_k")
        phase2 = per_detector(
            params.get("hwpss_phase_rad", 0.0), ctx.n_detectors, "hwpss_phase_rad"
        )
        argument = 2 * np.pi * ctx.times_s / float(params["period_s"])
        wave = np.sin(argument + params.get("phase_rad", 0))
        carrier = np.cos(2 * ctx.detector_angle - phase2[:, None])
        return tod + (relative * a2)[:, None] * wave[None, :] * carrier

    def on_true_hwpss(self, params, a2_true_k, a2_nominal_k, phase_rad):
        """It modulates the recording's true HWPSS: its amplitude and 2f phase."""
        return dict(params, a2_k=a2_true_k, hwpss_phase_rad=phase_rad)


@register
class PickupLine(Effect):
    """A cos(2 pi f t + phi): an electrical pickup line at a frequency of no HWP/scan combination."""

    name = "pickup_line"
    title = "electrical pickup line"
    parameters: ClassVar[dict[str, str]] = {"amplitude_k": "K", "freq_hz": "Hz", "phase_rad": "rad"}
    main_parameters = ("amplitude_k",)
    role = "outside"
    selectable = False
    signature = "a line at a frequency no HWP and spin combination makes"
    discrimination = "no catalog effect puts power there"

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
        phase = 2 * np.pi * float(params["freq_hz"]) * ctx.times_s + params.get("phase_rad", 0.0)
        return tod + amplitude[:, None] * np.cos(phase)[None, :]


@register
class HwpssSpinModulation(Effect):
    """c_n [1 + m cos(2 pi f_spin t)] cos n(chi - theta): an HWP harmonic modulated by the spin.

    (An HWP wobble whose emission depends on the spin phase.) Lines at n f_HWP and
    n f_HWP +- f_spin; not a catalog effect: only its constant part is hwpss_harmonics.
    """

    name = "hwpss_spin_modulation"
    title = "HWP harmonic modulated by the spin"
    parameters: ClassVar[dict[str, str]] = {"amplitude_k": "K", "harmonic": "1", "depth": "1"}
    main_parameters = ("amplitude_k",)
    role = "outside"
    selectable = False
    signature = "n f_HWP +- f_spin sidebands of an HWP harmonic"
    discrimination = (
        "the constant part is hwpss_harmonics; the sidebands follow no dipole (unlike the 4f "
        "intensity leakage)"
    )

    def apply(self, ctx, params, tod=None):
        tod = ctx.d_nom if tod is None else tod
        n = int(params.get("harmonic", 3))
        amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
        depth = float(params.get("depth", 1.0))
        envelope = 1.0 + depth * np.cos(2 * np.pi * ctx.f_spin_hz * ctx.times_s)
        return tod + amplitude[:, None] * envelope[None, :] * np.cos(n * ctx.detector_angle)
