"""Effects a simulated recording may carry that the diagnosis does not offer: a nominal
adjustment covers each (``role = "injection"``)."""

from __future__ import annotations

import math
from typing import ClassVar

from .base import Effect, _value, register


@register
class NoiseMismatch(Effect):
    """Noise unlike the configured one: P(f) = 2 w^2 (f^a + fk^a) / (f^a + fmin^a), one-sided.

    w = NET [K sqrt(s)] (white level, sigma per sample = w sqrt(f_s)), fk the knee, a the
    slope, fmin fixed at the configured value (litebird_sim's "toast" model). A simulated
    recording draws its noise with these (``{"net_ukrts", "fknee_mhz", "alpha"}``, one value
    or one per detector) instead of the detectors' own (:func:`..simulate.simulate_recording`).
    """

    name = "noise_mismatch"
    title = "noise unlike the configured NET / f_knee / alpha"
    parameters: ClassVar[dict[str, str]] = {"net": "K sqrt(s)", "fknee": "Hz", "alpha": "1"}
    main_parameters = ("net",)
    kind = "noise"
    stage = "noise"
    role = "injection"
    selectable = False  # the white level, knee and slope are nominal adjustments
    signature = "excess broadband power, no lines"
    discrimination = "smooth power spectrum change, explained by no template"


@register
class Crosstalk(Effect):
    """A fraction x of the other detector's signal: d_obs,k = d_k + x_k d_other(k)."""

    name = "crosstalk"
    title = "crosstalk from the other detector of the pair"
    parameters: ClassVar[dict[str, str]] = {"x": "1"}
    main_parameters = ("x",)
    role = "injection"
    selectable = False  # gain + A_2 + polarisation-efficiency adjustments in a pair
    min_detectors = 2
    signature = "the other detector's signal: its (antiphase) 2f HWPSS, dipole and polarisation"
    discrimination = (
        "in a pair sharing the pointing with orthogonal angles, x d_other = x (I + D) - x pol "
        "- x A_2 cos 2(chi - theta): exactly a gain, 2f amplitude and polarisation efficiency "
        "change, i.e. nominal adjustments (A_2 lowered by x A_2, gain raised by x); it is "
        "therefore not offered as an effect"
    )

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
