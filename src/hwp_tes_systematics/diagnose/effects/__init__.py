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

An effect is one class in one module of this package, registered by ``@register``
(:func:`.base.register`; the package imports every module): ``role`` "catalog" (the
diagnosis fits it, :data:`CATALOG`), "injection" (a simulated recording may carry it, a
nominal adjustment covers it, :data:`INJECTION_ONLY`: :mod:`.injection_only`, the
electrothermal TES) or "outside" (simulated only, the diagnosis must leave it in
``unexplained``: :mod:`.outside_catalog`). The catalog page (each effect's model in its
class docstring; its parameters, signature and how it is told from its look-alikes in its
attributes) is generated from the registries: ``python -m hwp_tes_systematics
effect-catalog`` prints it (:mod:`..catalog`; the documentation's effect catalog page).

How each parameter is fitted: jointly with the others, by (weighted) linear least
squares in the whitened Fourier domain for the linear effects; tau by
``scipy.optimize.least_squares`` from the linearised solution (variable projection over
the linear parameters); glitches by detection and a per-event nonlinear fit; the noise
by maximising the Whittle likelihood (see :mod:`.select` and :mod:`.noise`).
"""

from __future__ import annotations

import importlib
import pkgutil

from .base import (
    CATALOG,
    DRIFT_DEGREE,
    GAIN_DEGREES,
    HWPSS_HARMONICS,
    INJECTION_HARMONICS,
    INJECTION_ONLY,
    INJECTION_STAGES,
    MODULATION_MAX,
    MODULATION_MIN,
    MODULATION_STEP_S,
    NONLINEARITY_HARMONICS,
    OUTSIDE_CATALOG,
    REGISTRIES,
    SELECTION_THRESHOLD,
    Effect,
    format_temperature,
    modulation_degree,
    register,
    unregister,
)
from .crosstalk import DetectorCrosstalk
from .gain import (
    GainDrift,
    GainDriftCommon,
    GainDriftPerGroup,
    GainDriftSmooth,
    GainFluctuations,
)
from .glitches import (
    GLITCH_TAIL_CUT,
    Glitches,
    GlitchEvent,
    find_transients,
    fit_glitch,
    glitch_profile,
    glitch_tod,
)
from .hwpss import (
    HwpEmissionFluctuations,
    HwpIntensityLeakage4f,
    HwpssHarmonic,
    HwpssHarmonics,
    HwpssIntensityCoupling,
    HwpssSlowModulation,
    HwpTemperatureDrift,
    harmonic_templates,
)
from .nonlinearity import (
    TesNonlinearity,
    TesNonlinearityCubic,
)
from .pointing import PointingDrift, PointingOffset, PointingOffsetCommon, PointingOffsetPerGroup
from .steps import ReadoutSteps, StepEvent, find_steps, step_tod
from .time_constant import (
    DetectorTimeConstant,
    single_pole,
    single_pole_derivative,
)

# every module of this package: an effect registers itself (``@register``) in its own file
for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")


def reported_name(name: str) -> str:
    """The name the report gives an effect: its family's for a member (``reported_as``)."""
    return CATALOG[name].reported_as or name if name in CATALOG else name


def family_of(name: str) -> str:
    """The physics a name reports (:attr:`Effect.family`); a name outside the catalog (an
    injection-only effect) is its own family."""
    return CATALOG[name].family if name in CATALOG else name


def prior_penalty_of(name: str) -> float:
    """An effect's prior penalty (:attr:`Effect.prior_penalty`, added to its BIC); 0 for
    a name outside the catalog."""
    return CATALOG[name].prior_penalty if name in CATALOG else 0.0


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


__all__ = [
    "CATALOG",
    "DRIFT_DEGREE",
    "GAIN_DEGREES",
    "GLITCH_TAIL_CUT",
    "HWPSS_HARMONICS",
    "INJECTION_HARMONICS",
    "INJECTION_ONLY",
    "INJECTION_STAGES",
    "MODULATION_MAX",
    "MODULATION_MIN",
    "MODULATION_STEP_S",
    "NONLINEARITY_HARMONICS",
    "OUTSIDE_CATALOG",
    "REGISTRIES",
    "SELECTION_THRESHOLD",
    "DetectorCrosstalk",
    "DetectorTimeConstant",
    "Effect",
    "GainDrift",
    "GainDriftCommon",
    "GainDriftPerGroup",
    "GainDriftSmooth",
    "GainFluctuations",
    "GlitchEvent",
    "Glitches",
    "HwpEmissionFluctuations",
    "HwpIntensityLeakage4f",
    "HwpTemperatureDrift",
    "HwpssHarmonic",
    "HwpssHarmonics",
    "HwpssIntensityCoupling",
    "HwpssSlowModulation",
    "PointingDrift",
    "PointingOffset",
    "PointingOffsetCommon",
    "PointingOffsetPerGroup",
    "ReadoutSteps",
    "StepEvent",
    "TesNonlinearity",
    "TesNonlinearityCubic",
    "catalog_table",
    "family_of",
    "find_steps",
    "find_transients",
    "fit_glitch",
    "format_temperature",
    "get_effect",
    "glitch_profile",
    "glitch_tod",
    "harmonic_templates",
    "modulation_degree",
    "prior_penalty_of",
    "register",
    "reported_name",
    "single_pole",
    "single_pole_derivative",
    "step_tod",
    "unregister",
]


def noise_effect(signature: str) -> Effect:
    """The catalog's effect with this signature in the noise (``Effect.noise_signature``:
    "excess", "rolloff" or "correlation"), fitted beside the selection."""
    found = [e for e in CATALOG.values() if e.noise_signature == signature]
    if len(found) != 1:
        names = [e.name for e in found]
        raise LookupError(
            f"one catalog effect with noise_signature {signature!r} expected: {names}"
        )
    return found[0]
