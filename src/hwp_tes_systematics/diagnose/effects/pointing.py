"""Pointing offsets: the detectors look elsewhere than the recorded pointing says."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from .base import Effect, PerGroup, group_sentence, register

SECONDS_PER_HOUR = 3600.0


def _gradient(ctx) -> np.ndarray:
    if ctx.pointing_gradient is None:
        raise ValueError(
            "pointing offsets need the signal's gradient (Context.pointing_gradient), which "
            "model.build_context computes from the recording's pointings and the sky map"
        )
    return ctx.pointing_gradient


@register
class PointingOffset(Effect):
    """A fixed pointing offset: d_obs = d_nom + x dS/dx + y dS/dy, S = I(p) + P(p) + D(p).

    x, y [arcmin]: the pointing moved along the two directions fixed in the focal plane,
    u = cos psi e_theta + sin psi e_phi and v = -sin psi e_theta + cos psi e_phi (a rotation
    of the detector quaternion about the focal plane's x and y axes, as litebird_sim's
    pointing systematics make it). dS/dx: the dipole's gradient (exact, from litebird_sim)
    and the sky map's as the nominal model scans it (:func:`..model.pointing_gradients`),
    first order in the offset (the dipole's second-order term is ~ offset [rad] of the
    first: 1e-3 at 3.4 arcmin, measured in tests/diagnose/test_diagnose_pointing.py).
    """

    name = "pointing_offset"
    title = "pointing offset"
    parameters: ClassVar[dict[str, str]] = {"offset_x": "arcmin", "offset_y": "arcmin"}
    main_parameters = ("offset_x", "offset_y")
    # beyond a degree the pointing reconstruction has failed rather than drifted, and the
    # first-order template no longer describes the sky map's structure (assumption)
    physical_bounds: ClassVar[dict[str, float]] = {"offset_x": 60.0, "offset_y": 60.0}
    signature = (
        "residual equal to the gradient of the sky and the dipole along one direction fixed "
        "in the focal plane: at the spin frequency (the dipole moved, not scaled) and sharp "
        "where the sky map varies (the Galactic plane, compact sources)"
    )
    discrimination = (
        "a gain scales the dipole (in phase with it), an offset moves it (its gradient, a "
        "quarter of a spin period apart along the scan); a wrong sky map is an adjustment "
        "fixed on the sky and does not move the dipole, which the supplied map does not hold"
    )

    def templates(self, ctx):
        return _gradient(ctx).copy()

    def injection_stage(self, params):
        """A simulated recording moves its detectors (litebird_sim quaternions), not the
        first-order templates: :func:`..simulate.simulate_recording`."""
        return "pointing"

    def apply(self, ctx, params, tod=None):
        return self._linear_apply(ctx, params, tod)

    def _offset_sentence(self, fit, name, k) -> str:
        x, y = fit.values["offset_x"][k], fit.values["offset_y"][k]
        sx, sy = fit.sigmas["offset_x"][k], fit.sigmas["offset_y"][k]
        size = math.hypot(x, y)
        return (
            f"{name}: x = {x:.3g} +- {sx:.2g}, y = {y:.3g} +- {sy:.2g} arcmin "
            f"(|offset| {size:.3g} arcmin)"
        )

    def evidence(self, ev, fit) -> str:
        """The offsets per detector, and whether the pair moved together."""
        ctx = ev.ctx
        parts = [self._offset_sentence(fit, name, k) for k, name in enumerate(ctx.detector_names)]
        if ctx.n_detectors == 2:
            dx = np.diff(fit.values["offset_x"])[0]
            dy = np.diff(fit.values["offset_y"])[0]
            sigma = math.hypot(
                math.hypot(*fit.sigmas["offset_x"]), math.hypot(*fit.sigmas["offset_y"])
            )
            apart = math.hypot(dx, dy) / max(sigma, 1e-300)
            parts.append(
                f"the two detectors moved {'apart' if apart >= 3 else 'together'} "
                f"({apart:.1f} sigma): "
                + ("each its own offset" if apart >= 3 else "a boresight (focal plane) offset")
            )
        return "the residual follows the dipole's and the sky's gradient: " + "; ".join(parts)


@register
class PointingOffsetCommon(PointingOffset):
    """A pointing offset the same for every detector: the boresight (the focal plane) moved.

    The templates of :class:`PointingOffset` with one (x, y) for all detectors (``shared``):
    half the parameters, so a co-pointed pair's offset is found at ~1/sqrt(2) of the size
    that separate offsets need. Reported as ``pointing_offset``.
    """

    name = "pointing_offset_common"
    title = "boresight pointing offset"
    reported_as = "pointing_offset"
    shared = True
    signature = (
        "the pointing offset's signature, with the same offset in every detector (the "
        "boresight moved)"
    )
    discrimination = "separate offsets per detector fit no better (the detectors moved together)"

    def evidence(self, ev, fit) -> str:
        common = ", ".join(
            f"{p} = {fit.shared_values[p]:.3g} +- {fit.shared_sigmas[p]:.2g} arcmin"
            for p in ("offset_x", "offset_y")
        )
        return (
            f"the residual follows the dipole's and the sky's gradient, with one offset for "
            f"all detectors: {common} (sharing it costs chi^2 {fit.sharing_chi2:.1f} for "
            f"{fit.sharing_dof} fewer parameters): the boresight moved"
        )


@register
class PointingOffsetPerGroup(PerGroup, PointingOffsetCommon):
    """A pointing offset the same within each focal-plane group: a pixel's horn, a wafer's
    mount moved (``group_by``: one instance per key). The templates of
    :class:`PointingOffset` with one (x, y) per group; offered where the recording's
    detectors carry the key. Reported as ``pointing_offset``, with its scope."""

    signature = (
        "the pointing offset's signature, with the same offset in the detectors of one group"
    )
    discrimination = (
        "separate offsets per detector fit no better, one offset for all fits worse: the "
        "detectors of a group moved together"
    )

    group_keys = ("pixel", "wafer")
    base_name, base_title = "pointing_offset", "pointing offset"

    def evidence(self, ev, fit) -> str:
        return "the residual follows the dipole's and the sky's gradient, with " + group_sentence(
            self, fit, ("offset_x", "offset_y"), " arcmin"
        )


@register
class PointingDrift(PointingOffsetCommon):
    """The boresight offset drifting linearly: x(t) = x + x' (t - t_mid), the same for y.

    x', y' [arcmin/h], t_mid the middle of the recording; templates dS/dx (t - t_mid) / 1 h;
    one set for all detectors (a focal plane drifting, e.g. with its temperature).
    """

    name = "pointing_drift"
    title = "boresight pointing offset drifting in time"
    extends = "pointing_offset"
    reported_as = None
    parameters: ClassVar[dict[str, str]] = {
        "offset_x": "arcmin",
        "offset_y": "arcmin",
        "drift_x": "arcmin/h",
        "drift_y": "arcmin/h",
    }
    main_parameters = ("drift_x", "drift_y")
    physical_bounds: ClassVar[dict[str, float]] = {
        **PointingOffset.physical_bounds,
        "drift_x": 60.0,
        "drift_y": 60.0,
    }
    signature = "the pointing offset's signature, growing or changing sign in time"
    discrimination = (
        "a fixed offset has the same gradient template all along the recording; the drift "
        "weights it by the time from the middle of the recording"
    )

    def templates(self, ctx):
        gradient = _gradient(ctx)
        hours = (ctx.times_s - 0.5 * (ctx.times_s[0] + ctx.times_s[-1])) / SECONDS_PER_HOUR
        return np.concatenate([gradient, gradient * hours[None, None, :]], axis=1)

    def evidence(self, ev, fit) -> str:
        rates = ", ".join(
            f"{p} = {fit.shared_values[p]:.3g} +- {fit.shared_sigmas[p]:.2g} arcmin/h"
            for p in ("drift_x", "drift_y")
        )
        return super().evidence(ev, fit) + f", and drifts: {rates}"
