"""The TES gain nonlinearity: quadratic (the paper's model) and cubic."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ...instrument.nonlinearity import apply_nonlinearity
from .base import Effect, _value, format_temperature, register


@register
class TesNonlinearity(Effect):
    """d_obs = d + g1 d^2 on the total signal (TES gain compression; the paper's model).

    With d = A_2 cos x + D (x = 2 (chi - theta)): g1 d^2 = g1 A_2^2 / 2 (DC) +
    g1 A_2^2 / 2 cos 2x (4 f_HWP) + 2 g1 A_2 D cos x (for D = D0 cos 2 pi f_D t: two lines
    at 2 f_HWP +- f_D of amplitude g1 A_2 D0 each) + g1 D^2.
    """

    name = "tes_nonlinearity"
    title = "TES gain nonlinearity"
    parameters: ClassVar[dict[str, str]] = {"g1": "1/K"}
    # |g1| A_2 beyond ~0.1-0.2 (A_2 ~ 0.1-0.3 K): a detector compressed by more than ~15 %
    # over the HWPSS swing, outside the quadratic expansion's range (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"g1": 0.5}
    powers: ClassVar[tuple[int, ...]] = (2,)  # d_obs - d = sum_j p_j d^powers[j]
    main_parameters = ("g1",)
    stage = "response"
    signature_lines = ((4, 0), (2, -1), (2, 1))
    signature = (
        "4 f_HWP line g1 A_2^2/2 (and a DC shift, inside the offset), 2 f_HWP +- f_spin "
        "sidebands g1 A_2 D each"
    )
    discrimination = (
        "a 4f HWPSS harmonic has no sidebands (and is fitted jointly with it: the shared 4f "
        "line does not decide, the sidebands and d^2 do); intensity coupling has the "
        "sidebands but no 4f line and no DC, and a free phase (a_c, a_s: two parameters where "
        "g1 is one); the sidebands scale as A_2 I (not as I)"
    )

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


@register
class TesNonlinearityCubic(TesNonlinearity):
    """d_obs = d + g1 d^2 + g2 d^3: the quadratic model with a cubic term.

    g2 d^3 adds 3 g2 A_2^3 / 4 cos x (2 f_HWP) and g2 A_2^3 / 4 cos 3x (6 f_HWP). The
    quadratic ``tes_nonlinearity`` is its nested special case (g2 = 0): the selection keeps
    whichever the BIC prefers, so g2 is reported only when its lines pay for it.
    """

    name = "tes_nonlinearity_cubic"
    title = "TES gain nonlinearity with a cubic term"
    parameters: ClassVar[dict[str, str]] = {"g1": "1/K", "g2": "1/K^2"}
    physical_bounds: ClassVar[dict[str, float]] = {"g1": 0.5, "g2": 5.0}  # K^-1, K^-2 (assumption)
    powers: ClassVar[tuple[int, ...]] = (2, 3)
    extends = "tes_nonlinearity"
    signature = TesNonlinearity.signature + ", 6 f_HWP line g2 A_2^3/4"
    discrimination = (
        "tes_nonlinearity is its nested special case (g2 = 0): the BIC keeps the cubic term "
        "only when its own lines pay for g2 (the backward step drops the other)"
    )


@register
class TesElectrothermal(Effect):
    """The nonlinearity through the electrothermal TES model: optical power P = P0 + d / C
    [W], current I = I(P) from ``tes.solve_operating_point`` and the linearly calibrated
    response d_rec = C [I(P) - I(P0)] / S0, S0 = dI/dP at P0, C [K/W].

    Simulated recordings only (``role = "injection"``): the diagnosis fits its Taylor
    expansion, ``tes_nonlinearity`` (and ``tes_nonlinearity_cubic``). ``tes_parameters``
    given are used as they are; otherwise the channel's TES is built from ``p0_w`` with
    ``psat_factor`` (default 2.5), ``resistance_fraction`` (0.7) and ``overrides``.
    """

    name = "tes_electrothermal"
    title = "TES nonlinearity through the electrothermal model"
    parameters: ClassVar[dict[str, str]] = {"p0_w": "W", "kelvin_per_watt": "K/W"}
    main_parameters = ("p0_w",)
    stage = "response"
    role = "injection"
    selectable = False
    signature = TesNonlinearity.signature
    discrimination = "the diagnosis reads it as tes_nonlinearity (cubic where d^3 shows)"

    def apply(self, ctx, params, tod=None):
        from scipy.interpolate import CubicSpline

        from ...instrument import tes

        tod = ctx.d_nom if tod is None else tod
        p0_w = float(params["p0_w"])
        kelvin_per_watt = float(params["kelvin_per_watt"])
        tes_params = params.get("tes_parameters")
        if tes_params is None:
            tes_params = tes.tes_parameters_for_channel(
                p0_w,
                psat_factor=float(params.get("psat_factor", 2.5)),
                resistance_fraction=float(params.get("resistance_fraction", 0.7)),
                **dict(params.get("overrides", {})),
            )
        power_w = p0_w + tod / kelvin_per_watt
        lo, hi = float(power_w.min()), float(power_w.max())
        margin = 0.01 * (hi - lo) + 1e-18
        grid = np.linspace(max(lo - margin, 0.0), hi + margin, 2001)
        spline = CubicSpline(grid, tes.solve_operating_point(tes_params, grid).current_a)
        current0 = float(tes.solve_operating_point(tes_params, p0_w).current_a)
        responsivity0 = float(tes.responsivity_a_per_w(tes_params, p0_w))
        return kelvin_per_watt * (spline(power_w) - current0) / responsivity0
