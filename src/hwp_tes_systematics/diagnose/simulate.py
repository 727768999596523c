"""Recordings with a known truth: a detector pair simulated with litebird_sim, with effects
injected through the catalog's own forward models, and the effects a simulation can inject
that the diagnosis does not offer.

:func:`simulate_recording` makes a recording with :class:`~hwp_tes_systematics.simulation.tod.PairSimulator`
(sky + dipole + HWPSS + noise) and injects effects of the catalog through the same
forward models (:mod:`.effects`), or a TES nonlinearity through the electrothermal model
(``tes_electrothermal``): optical power P = P0 + d / C [W], current I = I(P) from
``tes.solve_operating_point`` and the linearly calibrated response
d_rec = C [I(P) - I(P0)] / S0, S0 = dI/dP at P0, C [K/W].

Injection order: a pointing offset (the sky and dipole scanned where the rotated
detectors look) -> effects on the sky signal (time constant, HWPSS harmonics, intensity
coupling, gain, HWP temperature, crosstalk, in the order given) -> + noise (white + 1/f,
litebird_sim, its own seed; ``noise_mismatch`` changes its NET/f_knee/alpha) -> a time
constant ``through_noise`` (on signal and noise) -> detector
nonlinearity (polynomial or electrothermal) on the total -> + glitches.

Injection only (never offered by the selection): ``noise_mismatch`` (the white level,
knee and slope are nominal adjustments), ``crosstalk`` (in a co-pointed orthogonal pair,
exactly a gain, 2f-amplitude and polarisation-efficiency change: nominal adjustments),
``tes_electrothermal`` (the nonlinearity through the TES model) and the effects OUTSIDE
the catalog (:data:`OUT_OF_CATALOG`: a periodic 2f modulation, a pickup line, a
spin-modulated HWP harmonic), which the diagnosis must leave in ``unexplained``.
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import asdict
from typing import ClassVar

import numpy as np

from .. import seeding
from ..simulation import data_model
from .effects import (
    CATALOG,
    RESPONSE_STAGE,
    SIGNAL_EFFECTS,
    Effect,
    GlitchEvent,
)
from .effects.base import _value
from .model import Context, per_detector
from .recording import DEFAULT_START_TDB, Recording, _json_safe


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


INJECTION_ONLY: dict[str, Effect] = {e.name: e for e in (NoiseMismatch(), Crosstalk())}
# the effects on the optical signal, applied before the noise and the detector's response
SIGNAL_STAGE = SIGNAL_EFFECTS | {n for n, e in INJECTION_ONLY.items() if e.stage == "signal"}


def injectable(name: str) -> Effect:
    """The catalog's or an injection-only effect called ``name``."""
    effect = CATALOG.get(name) or INJECTION_ONLY.get(name)
    if effect is None:
        raise KeyError(
            f"unknown effect {name!r}; the catalog has {sorted(CATALOG)}, "
            f"injection only {sorted(INJECTION_ONLY)}"
        )
    return effect


@functools.lru_cache(maxsize=4)
def _simulated_base(channel_name: str, hours: float, start_time_tdb: str, nside: int):
    """PairSimulator, pointing and dipole of a recording (noise-free pieces), cached."""
    from ..instrument.channels import load_channel
    from ..simulation.tod import MissionPlan, PairSimulator

    channel = load_channel(channel_name)
    duration_s = hours * 3600.0
    plan = MissionPlan(start_time_tdb, duration_s, duration_s, channel.sampling_rate_hz)
    simulator = PairSimulator(channel, plan, nside)
    pointing = simulator.pointing(0, plan.n_samples)
    dipole = simulator.dipole(pointing)
    return simulator, pointing, dipole


# injected by moving the detectors (litebird_sim quaternions), not through the catalog's
# first-order templates: the recording keeps the nominal pointing
POINTING_EFFECTS = frozenset({"pointing_offset", "pointing_drift"})


def _rotation_quats(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    """(n, 4) litebird_sim quaternions (x, y, z, w) of rotations by ``angle_rad`` about the
    x (axis 0) or y (axis 1) axis."""
    quats = np.zeros((angle_rad.size, 4))
    quats[:, axis] = np.sin(0.5 * angle_rad)
    quats[:, 3] = np.cos(0.5 * angle_rad)
    return quats


def _true_pointing(simulator, pointing, params: dict):
    """The pointing of a pair whose detectors are rotated about the focal plane's x and y
    axes by x(t) = offset_x + drift_x (t - t_mid) [arcmin, arcmin/h] (and y), as
    litebird_sim's pointing systematics do it (``RotQuaternion * detector quat``); one
    offset per detector or one for both."""
    import litebird_sim as lbs

    from ..simulation.tod import QUATERNION_STEP_S
    from .model import ARCMIN_RAD

    n_det = simulator.n_detectors
    n = pointing.hwp_angle_rad.size
    fs = simulator.plan.sampling_rate_hz
    # a drift is sampled as the spin-axis quaternions are (litebird_sim multiplies the two)
    spin = simulator.scanning.spin_to_ecliptic(
        simulator.plan.start_time, n / fs + 2 * QUATERNION_STEP_S
    )
    n_quats = spin.quats.shape[0]
    mid_s = 0.5 * (n - 1) / fs
    hours = (np.arange(n_quats) / spin.sampling_rate_hz - mid_s) / 3600.0
    timing = {"start_time": spin.start_time, "sampling_rate_hz": spin.sampling_rate_hz}
    moved = copy.copy(simulator)
    moved.detectors = [copy.deepcopy(d) for d in simulator.detectors]
    for k, detector in enumerate(moved.detectors):
        for axis, name in enumerate("xy"):
            offset = _value(params, f"offset_{name}", n_det)[k]
            rate = _value(params, f"drift_{name}", n_det)[k]
            if offset == 0 and rate == 0:
                continue
            if rate == 0:
                angle = np.array([offset * ARCMIN_RAD])
                rotation = lbs.RotQuaternion(quats=_rotation_quats(axis, angle))
            else:
                angle = (offset + rate * hours) * ARCMIN_RAD
                rotation = lbs.RotQuaternion(quats=_rotation_quats(axis, angle), **timing)
                if detector.quat.quats.shape[0] == 1:  # a time-dependent product needs both
                    detector.quat = lbs.RotQuaternion(
                        quats=np.repeat(detector.quat.quats, n_quats, axis=0), **timing
                    )
            detector.quat = rotation * detector.quat
    return moved.pointing(0, n), moved


def _detector_dicts(simulator) -> list[dict]:
    return [_json_safe(asdict(detector)) for detector in simulator.detectors]


def _electrothermal(tod: np.ndarray, params: dict) -> np.ndarray:
    """d_rec = C [I(P0 + d / C) - I(P0)] / S0 through the electrothermal TES model."""
    from scipy.interpolate import CubicSpline

    from ..instrument import tes

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


def _noise(simulator, pointing, master_seed, noise_seed, params: dict | None) -> np.ndarray:
    """White + 1/f noise of litebird_sim (chunk 0 streams of PairSimulator.noise)."""
    if not params:
        return simulator.noise(pointing, master_seed, noise_seed, 0)
    from litebird_sim.noise import add_one_over_f_noise

    channel = simulator.channel
    n = pointing.hwp_angle_rad.size
    n_det = simulator.n_detectors
    out = np.zeros((n_det, n))
    detectors = simulator.detectors

    def value(key):
        default = [getattr(d, key) for d in detectors]
        return per_detector(params.get(key, default), n_det, key)

    net, fknee, alpha, fmin = (value(key) for key in ("net_ukrts", "fknee_mhz", "alpha", "fmin_hz"))
    for k, name in enumerate(simulator.detector_names):
        generator = seeding.rng(master_seed, "noise", channel.name, noise_seed, 0, name)
        sigma = net[k] * np.sqrt(channel.sampling_rate_hz) / 1e6
        add_one_over_f_noise(
            out[k], fknee[k], fmin[k], alpha[k], sigma, channel.sampling_rate_hz, generator
        )
    return out


RESPONSE_EFFECTS = RESPONSE_STAGE | {"tes_electrothermal"}


def _hwpss_sine_modulation(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """A_2 [1 + m sin(2 pi t / P + phi)] cos(2 (chi - theta) - phi_2): a periodic 2f modulation.

    Modulates the recording's actual HWPSS: ``a2_k`` and ``hwpss_phase_rad`` (phi_2), when
    given, are its true amplitude and phase (default: the nominal ones).
    """
    relative = per_detector(params["relative"], ctx.n_detectors, "relative")
    a2 = per_detector(params.get("a2_k", ctx.a2_k), ctx.n_detectors, "a2_k")
    phase2 = per_detector(params.get("hwpss_phase_rad", 0.0), ctx.n_detectors, "hwpss_phase_rad")
    wave = np.sin(2 * np.pi * ctx.times_s / float(params["period_s"]) + params.get("phase_rad", 0))
    carrier = np.cos(2 * ctx.detector_angle - phase2[:, None])
    return tod + (relative * a2)[:, None] * wave[None, :] * carrier


def _pickup_line(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """A cos(2 pi f t + phi): an electrical pickup line at a frequency of no HWP/scan combination."""
    amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
    phase = 2 * np.pi * float(params["freq_hz"]) * ctx.times_s + params.get("phase_rad", 0.0)
    return tod + amplitude[:, None] * np.cos(phase)[None, :]


def _hwpss_spin_modulation(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """c_n [1 + m cos(2 pi f_spin t)] cos n(chi - theta): an HWP harmonic modulated by the spin.

    (An HWP wobble whose emission depends on the spin phase.) Lines at n f_HWP and
    n f_HWP +- f_spin; not a catalog effect: only its constant part is hwpss_harmonics.
    """
    n = int(params.get("harmonic", 3))
    amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
    depth = float(params.get("depth", 1.0))
    envelope = 1.0 + depth * np.cos(2 * np.pi * ctx.f_spin_hz * ctx.times_s)
    return tod + amplitude[:, None] * envelope[None, :] * np.cos(n * ctx.detector_angle)


# Effects OUTSIDE the catalog (no forward model in the diagnosis), for tests and benchmarks:
# signal effects, applied with the catalog's signal effects before the noise.
OUT_OF_CATALOG = {
    "hwpss_sine_modulation": _hwpss_sine_modulation,
    "pickup_line": _pickup_line,
    "hwpss_spin_modulation": _hwpss_spin_modulation,
}


def _filters_noise(name: str, params: dict) -> bool:
    """A time constant injected with ``through_noise``: it acts on the optical signal and
    the detector noise together (photon and phonon noise pass the TES's pole), before the
    nonlinearity, instead of on the signal alone."""
    return name == "detector_time_constant" and bool(params.get("through_noise", False))


def simulate_recording(
    channel_name: str,
    hours: float,
    master_seed: int,
    noise_seed: int,
    sky_iqu: np.ndarray,
    a2_k,
    effects=(),
    start_time_tdb: str = DEFAULT_START_TDB,
    pol_angle_offsets_rad=0.0,
) -> Recording:
    """A recording of ``channel_name``'s pair: sky + dipole + HWPSS + noise + injected effects.

    ``effects`` is a list of (name, params): catalog effects with their parameters (a
    scalar or one value per detector each; glitches as ``{"events": [(detector, time_s,
    amplitude_k, tau_s), ...]}``; noise_mismatch as ``{"net_ukrts", "fknee_mhz",
    "alpha"}``; pointing_offset / pointing_drift as ``{"offset_x", "offset_y", "drift_x",
    "drift_y"}`` [arcmin, arcmin/h], injected by rotating the detector quaternions while
    the recording keeps the nominal pointing), or ``("tes_electrothermal", {"p0_w",
    "kelvin_per_watt", ...})``; a ``detector_time_constant`` with ``"through_noise": True``
    filters the noise as well (the noise then rolls off: :mod:`.rolloff`). The noise comes from its own stream ``(master_seed, "noise", channel, noise_seed, 0,
    detector)``. The truth is kept in ``recording.injected`` (never written to a file).
    ``pol_angle_offsets_rad``: the true polarisation angles are theta + delta while the
    recording's metadata keeps the nominal theta (a polarisation-angle error): the sky
    polarisation is rho [Q cos 2(a - delta) + U sin 2(a - delta)] and the HWPSS
    A_2 cos 2(chi - theta - delta).
    """
    from .model import check_sky_map

    sky = check_sky_map(sky_iqu)
    nside = round(np.sqrt(sky.shape[1] / 12))
    simulator, pointing, dipole = _simulated_base(channel_name, float(hours), start_time_tdb, nside)
    n_det = simulator.n_detectors
    a2 = per_detector(a2_k, n_det, "a2_k")
    unpolarized = np.stack([sky[0], np.zeros_like(sky[0]), np.zeros_like(sky[0])])
    recorded_pointing = pointing
    effects = [(str(name), dict(params)) for name, params in effects]
    moves = [params for name, params in effects if name in POINTING_EFFECTS]
    if len(moves) > 1:
        raise ValueError("inject one pointing_offset or pointing_drift, not several")
    if moves:  # the detectors look elsewhere; the recording keeps the nominal pointing
        pointing, moved = _true_pointing(simulator, pointing, moves[0])
        dipole = moved.dipole(pointing)
    sky_intensity = simulator.scan_sky(pointing, unpolarized)
    sky_polarization = simulator.scan_sky(pointing, sky) - sky_intensity
    delta = per_detector(pol_angle_offsets_rad, n_det, "pol_angle_offsets_rad")
    if np.any(delta != 0):
        quadrature = data_model.scan_quadrature(
            pointing.pixels,
            pointing.cos_2alpha,
            pointing.sin_2alpha,
            simulator.pol_efficiency,
            sky,
        )
        sky_polarization = (
            np.cos(2 * delta)[:, None] * sky_polarization + np.sin(2 * delta)[:, None] * quadrature
        )
    pol_angles = simulator.pol_angles_rad + delta
    n = pointing.hwp_angle_rad.size
    ctx = Context(
        times_s=np.arange(n) / simulator.plan.sampling_rate_hz,
        sampling_rate_hz=simulator.plan.sampling_rate_hz,
        hwp_angle_rad=pointing.hwp_angle_rad,
        pol_angle_rad=pol_angles,
        pol_efficiency=simulator.pol_efficiency,
        sky_intensity=sky_intensity,
        sky_polarization=sky_polarization,
        dipole=dipole,
        a2_k=a2,
        valid=np.ones((n_det, n), dtype=bool),
        detector_names=simulator.detector_names,
    )
    # The HWPSS of the data model (litebird_sim's add_2f), as the study's simulation.
    hwpss = data_model.hwpss(pointing.hwp_angle_rad, pol_angles, a2)
    signal = sky_intensity + sky_polarization + dipole + hwpss

    for name, _ in effects:
        known = CATALOG.keys() | INJECTION_ONLY.keys() | RESPONSE_EFFECTS | OUT_OF_CATALOG.keys()
        if name not in known:
            raise KeyError(
                f"unknown effect {name!r}; expected one of {sorted(CATALOG)}, "
                f"{sorted(INJECTION_ONLY)}, {sorted(RESPONSE_EFFECTS)} or {sorted(OUT_OF_CATALOG)}"
            )
    for name, params in effects:
        if _filters_noise(name, params):
            continue  # below, on signal and noise
        if name in SIGNAL_STAGE and name not in POINTING_EFFECTS:
            signal = injectable(name).apply(ctx, params, signal)
        elif name in OUT_OF_CATALOG:
            signal = OUT_OF_CATALOG[name](ctx, params, signal)
    noise_params = next((p for name, p in effects if name == "noise_mismatch"), None)
    tod = signal + _noise(simulator, pointing, master_seed, noise_seed, noise_params)
    for name, params in effects:  # a time constant the detector noise also passes through
        if _filters_noise(name, params):
            tod = injectable(name).apply(ctx, params, tod)
    for name, params in effects:
        if name in RESPONSE_STAGE:
            tod = injectable(name).apply(ctx, params, tod)
        elif name == "tes_electrothermal":
            tod = _electrothermal(tod, params)
    for name, params in effects:
        if name == "glitches":
            events = [
                e if isinstance(e, GlitchEvent) else GlitchEvent(*e) for e in params["events"]
            ]
            tod = injectable(name).apply(ctx, {"events": events}, tod)

    return Recording(
        tod=tod,
        times_s=ctx.times_s.copy(),
        sampling_rate_hz=float(simulator.plan.sampling_rate_hz),
        hwp_angle_rad=np.array(recorded_pointing.hwp_angle_rad, dtype=float),
        pointings_ecl=np.array(recorded_pointing.ecliptic_rad(), dtype=float),
        detectors=_detector_dicts(simulator),
        start_time=simulator.plan.start_time,
        flags=np.zeros((n_det, n), dtype=bool),
        channel=channel_name,
        source=f"<simulated {channel_name}, {hours:g} h, noise seed {noise_seed}>",
        observation=recorded_pointing.observation,
        injected=effects,
    )
