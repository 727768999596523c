"""The effect interface (:class:`Effect`), the registries effects join (:func:`register`),
and what every effect shares: the per-detector parameter helper, temperature formatting,
the harmonic and degree choices."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from ..model import Context, per_detector
from ..recording import GROUP_KEYS

HWPSS_HARMONICS = (1, 3, 4, 5, 6)  # n = 2 is the nominal 2f adjustment
NONLINEARITY_HARMONICS = (4, 6)  # the HWPSS lines d^2 and d^3 make of a 2f HWPSS
INJECTION_HARMONICS = (1, 2, 3, 4, 5, 6)  # a simulated recording may carry any of them
GAIN_DEGREES = (1, 2, 3)  # g0 (a constant gain error) is the nominal gain adjustment
DRIFT_DEGREE = 3  # hwp_temperature_drift: P1..P3
SELECTION_THRESHOLD = -10.0  # the selection's default Delta BIC threshold (fit.DELTA_BIC_THRESHOLD)
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


# The order in which a simulated recording carries its effects
# (:func:`..simulate.simulate_recording`): the detectors moved, the optical signal, the
# detector noise, a response on signal and noise together, the detector's response to the
# total, transients added after it. ``Effect.injection_stage`` names an effect's.
INJECTION_STAGES = ("pointing", "signal", "noise", "through_noise", "response", "events")


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
    # where :func:`register` puts it: "catalog" (the diagnosis fits it, :data:`CATALOG`),
    # "injection" (simulated recordings only: a nominal adjustment covers it,
    # :data:`INJECTION_ONLY`) or "outside" (simulated recordings only: the diagnosis has no
    # model of it and must leave it in ``unexplained``, :data:`OUTSIDE_CATALOG`)
    role: ClassVar[str] = "catalog"
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
    # a shared effect's scope: one set of parameters per group of this focal-plane key
    # (:data:`.recording.GROUP_KEYS`: a wafer's bath, a readout line, a pixel's horn), or
    # None: one set for all detectors; offered where the recording has the key's groups
    group_by: str | None = None
    # -2 ln(prior odds) against the effect, added to its BIC (0: none; see GainDriftCommon)
    prior_penalty: float = 0.0
    # the fewest detectors a recording needs for the fit to offer it (crosstalk: a pair)
    min_detectors: ClassVar[int] = 1
    # its signature in the noise of the residual, fitted beside the selection's effects
    # (:func:`..select.step.select_effects`): "excess" (excess power in the sidebands of the
    # HWPSS, a random process) or "rolloff" (the noise rolling off, a pole); else None
    noise_signature: ClassVar[str | None] = None
    # True: offered only once the noise is refitted on the residual of the first selection
    # pass (:func:`..select.step.select_effects`): a search for events finds false ones
    # where the first noise, fitted before any effect was removed, misses power
    after_noise_refit: ClassVar[bool] = False

    @classmethod
    def instances(cls) -> tuple[Effect, ...]:
        """The effects :func:`register` adds for this class: one (a parametrised class, one
        per parameter value, e.g. a line per HWP harmonic)."""
        return (cls(),)

    def fit_noise(self, ctx: Context, residual_f, noise, used, ln_n_eff: float, **options):
        """The fit of its noise signature to the residual's rfft ``residual_f`` per detector,
        beside the noise models ``noise`` (its fit's result has ``delta_bic`` and
        ``delta_chi2`` against the noise alone); ``used`` the modes of the likelihood."""
        raise NotImplementedError(f"{self.name} has no signature in the noise")

    def noise_entry(self, ctx: Context, fit, noise) -> dict:
        """The report's entry for its fitted noise signature ``fit`` (:meth:`fit_noise`)."""
        raise NotImplementedError(f"{self.name} has no signature in the noise")

    def injection_stage(self, params: dict) -> str:
        """Where a simulated recording injects it with ``params`` (:data:`INJECTION_STAGES`):
        its ``stage``."""
        return self.stage

    def on_true_hwpss(self, params: dict, a2_true_k, a2_nominal_k: float, phase_rad) -> dict:
        """The parameters of an effect injected into a recording whose true HWPSS has
        amplitude ``a2_true_k`` [K] and 2f phase ``phase_rad`` (one each per detector) where
        ``params`` were given for the nominal ``a2_nominal_k``: unchanged, unless the effect
        acts on the HWPSS itself (:func:`..testbed.recorded_with_errors`)."""
        return params

    def shared_scale(self, ctx: Context) -> np.ndarray:
        """s_k of a shared effect, (n_det,): detector k's parameters are s_k times the common ones."""
        return np.ones(ctx.n_detectors)

    def shared_groups(self, ctx: Context) -> dict[str, np.ndarray]:
        """{group label: its detectors' indices} of a shared effect: one group "all" of
        every detector, or the groups of ``group_by`` (``ctx.groups``)."""
        if self.group_by is None:
            return {"all": np.arange(ctx.n_detectors)}
        labels = np.asarray(ctx.groups[self.group_by])
        return {label: np.flatnonzero(labels == label) for label in dict.fromkeys(labels)}

    def scope(self, ctx: Context, fit=None) -> dict:
        """The report's scope: {"by": "detector", "all" or the group key, "groups":
        {label: detector names}} (no groups for "detector"); ``fit``, its fit, for an
        effect whose scope the fit decides (glitches shared by detectors)."""
        if not self.shared:
            return {"by": "detector", "groups": {}}
        names = np.asarray(ctx.detector_names)
        return {
            "by": self.group_by or "all",
            "groups": {
                str(label): names[members].tolist()
                for label, members in self.shared_groups(ctx).items()
            },
        }

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

    # its own lines, (n, m) for n f_HWP + m f_spin: one of them left in `unexplained` after
    # the fit means the effect describes those lines only in part (said in the report)
    signature_lines: ClassVar[tuple[tuple[int, int], ...]] = ()
    # |parameter| beyond which the effect is not physics but a template absorbing something
    # else (e.g. an intensity coupling of 0.35): parameter -> bound, in its unit
    physical_bounds: ClassVar[dict[str, float]] = {}
    # its parameters describe events at times (a recording diagnosed in segments keeps
    # them per segment instead of averaging them: :mod:`..segments`)
    events: ClassVar[bool] = False

    def complete_events(self, problem, events: list, residual_of) -> list:
        """An events effect's events of every detector (``find``'s, each in its own
        residual) completed by what the detectors share (readout steps at a bias line's
        time); ``residual_of(k)`` gives detector k's (rfft, bank, gram) as ``find`` took
        them. As found by default."""
        return events

    def unphysical(self, fit) -> str | None:
        """Why the fitted values (:class:`.select.EffectFit`) are outside ``physical_bounds``,
        or None: the selection does not take an effect whose parameters are unphysical."""
        for parameter, bound in self.physical_bounds.items():
            values = np.abs(np.asarray(fit.values.get(parameter, [])))
            if values.size and values.max() > bound:
                return f"|{parameter}| = {values.max():.3g} > {bound:g}"
        return None

    def before_events(self, fit, ctx: Context, a2_before_k: np.ndarray):
        """``fit`` with its relative parts referred to the signal before the effect's events,
        whose 2f HWPSS amplitude is ``a2_before_k`` per detector (the adjusted nominal A_2
        was fitted to a recording that holds the events); unchanged by default."""
        return fit

    def reported_parameters(self, fit, detector_names, sampling_rate_hz, units) -> dict:
        """The report's parameters of a fit (:class:`.select.EffectFit`): "<parameter>[<detector>]"
        -> {value, sigma, unit, detector, parameter}, and a shared effect's common ones as
        "<parameter>[common]"."""
        out = {}
        for param, unit in units.items():
            for k, det in enumerate(detector_names):
                entry = {
                    "value": float(fit.values[param][k]),
                    "sigma": float(fit.sigmas[param][k]),
                    "unit": unit,
                    "detector": det,
                    "parameter": param,
                }
                out[f"{param}[{det}]"] = entry
        for param, value in fit.shared_values.items():  # a shared effect's common parameters
            out[f"{param}[common]"] = {
                "value": value,
                "sigma": fit.shared_sigmas[param],
                "unit": fit.shared_units[param],
                "detector": "common",
                "parameter": param,
            }
        for label, values in fit.group_values.items():  # or each group's
            for param, value in values.items():
                group = f"{self.group_by} {label}"
                out[f"{param}[{group}]"] = {
                    "value": value,
                    "sigma": fit.group_sigmas[label][param],
                    "unit": fit.shared_units[param],
                    "detector": group,
                    "parameter": param,
                }
        return out

    def evidence(self, ev, fit) -> str:
        """The signature measured on the residual ``ev`` (:class:`.evidence.Evidence`), in words."""
        return self.signature

    def unresolved_look_alikes(self, ev, fit) -> list[str]:
        """Catalog effects this fit cannot be told from because the signature that would
        tell them apart is below detection in this recording (none by default)."""
        return []

    def __repr__(self) -> str:
        return f"<effect {self.name}>"


# The registries, filled by :func:`register` in the order the effect modules are imported.
CATALOG: dict[str, Effect] = {}  # the effects the diagnosis fits
INJECTION_ONLY: dict[str, Effect] = {}  # simulated only: a nominal adjustment covers them
OUTSIDE_CATALOG: dict[str, Effect] = {}  # simulated only: the diagnosis has no model of them
REGISTRIES = {"catalog": CATALOG, "injection": INJECTION_ONLY, "outside": OUTSIDE_CATALOG}


class PerGroup:
    """Mixin of a shared effect's per-group form: one instance per focal-plane key of
    ``group_keys`` (:data:`GROUP_KEYS`), named "<base_name>_per_<key>"."""

    group_keys: ClassVar[tuple[str, ...]] = ()
    base_name: ClassVar[str] = ""
    base_title: ClassVar[str] = ""

    def __init__(self, key: str):
        self.group_by = key
        self.name = f"{self.base_name}_per_{key}"
        self.title = f"{self.base_title} common to each {GROUP_KEYS[key]}"

    @classmethod
    def instances(cls) -> tuple:
        return tuple(cls(key) for key in cls.group_keys)


def detector_partitions(ctx: Context) -> dict[str, dict[str, np.ndarray]]:
    """The ways to split a recording's detectors into groups: {"all": {"all": every
    detector}} and, for each focal-plane key it carries, {key: {label: its detectors}}."""
    partitions = {"all": {"all": np.arange(ctx.n_detectors)}}
    for key, labels in ctx.groups.items():
        labels = np.asarray(labels)
        partitions[key] = {str(g): np.flatnonzero(labels == g) for g in dict.fromkeys(labels)}
    return partitions


def partition_scope(ctx: Context, by: str, groups: dict) -> dict:
    """The report's scope (:meth:`Effect.scope`) of a partition ``by`` with its ``groups``."""
    names = np.asarray(ctx.detector_names)
    return {"by": by, "groups": {label: names[m].tolist() for label, m in groups.items()}}


def other_partitions(values: dict[str, float], by: str, all_text: str) -> str:
    """How much worse (in -2 ln L or chi^2) each partition but ``by`` fits, in words;
    ``all_text`` names the partition of all detectors in one group."""
    return "; ".join(
        (all_text if key == "all" else f"per {GROUP_KEYS[key]}")
        + f" fits worse by chi^2 {value - values[by]:.1f}"
        for key, value in values.items()
        if key != by
    )


def group_sentence(effect: Effect, fit, parameters, unit: str) -> str:
    """The sentence stating a per-group effect's values, ``parameters`` of each group in
    ``unit``, and what sharing them within the groups cost (:attr:`Effect.group_by`)."""
    groups = "; ".join(
        f"{effect.group_by} {label}: "
        + ", ".join(
            f"{p} = {values[p]:.3g} +- {fit.group_sigmas[label][p]:.2g}{unit}" for p in parameters
        )
        for label, values in fit.group_values.items()
    )
    return (
        f"one set per {GROUP_KEYS[effect.group_by]} ({groups}); sharing it within the "
        f"groups costs chi^2 {fit.sharing_chi2:.1f} for {fit.sharing_dof} fewer parameters"
    )


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: ``cls.instances()`` join the registry of ``cls.role``. An effect is
    one registered class in one file of this package (the package imports every module):
    the diagnosis, the simulator, the catalog page and the CLI find it there."""
    if cls.role not in REGISTRIES:
        raise ValueError(
            f"{cls.__name__}.role = {cls.role!r}; expected one of {sorted(REGISTRIES)}"
        )
    for effect in cls.instances():
        for role, registry in REGISTRIES.items():
            if effect.name in registry:
                raise ValueError(
                    f"{cls.__name__}: an effect named {effect.name!r} is registered already "
                    f"({type(registry[effect.name]).__name__}, role {role!r})"
                )
        REGISTRIES[cls.role][effect.name] = effect
    return cls


def unregister(cls: type[Effect]) -> None:
    """Remove the effects of exactly ``cls`` from the registries (a test's own effect)."""
    for registry in REGISTRIES.values():
        for name in [n for n, e in registry.items() if type(e) is cls]:
            del registry[name]
