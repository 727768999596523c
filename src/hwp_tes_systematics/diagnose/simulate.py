"""Recordings with a known truth: a detector pair simulated with litebird_sim, with effects
injected through the effects' own forward models.

:func:`simulate_recording` makes a recording with :class:`~hwp_tes_systematics.simulation.tod.PairSimulator`
(sky + dipole + HWPSS + noise) and injects each effect given by name through its class
(:mod:`.effects`: the catalog's, the injection-only ones a nominal adjustment covers, and
those outside the catalog the diagnosis must leave in ``unexplained``), at the effect's
own stage (``Effect.injection_stage``), in the order of
:data:`.effects.base.INJECTION_STAGES`: a pointing offset or drift (the sky and dipole
scanned where the rotated detectors look) -> effects on the optical signal (in the order
given) -> + noise (white + 1/f, litebird_sim, its own seed; ``noise_mismatch`` changes
its NET/f_knee/alpha) -> a time constant ``through_noise`` (on signal and noise) ->
the detector's response to the total (polynomial or electrothermal nonlinearity) ->
+ glitches.
"""

from __future__ import annotations

import copy
import functools
from dataclasses import asdict

import numpy as np

from .. import seeding
from ..simulation import data_model
from .effects import CATALOG, INJECTION_ONLY, INJECTION_STAGES, OUTSIDE_CATALOG, REGISTRIES, Effect
from .effects.base import _value
from .model import Context, per_detector
from .recording import DEFAULT_START_TDB, Recording, _json_safe


def injectable(name: str) -> Effect:
    """The effect called ``name``: the catalog's, an injection-only one or one outside the
    catalog (:data:`.effects.base.REGISTRIES`)."""
    for registry in REGISTRIES.values():
        if name in registry:
            return registry[name]
    raise KeyError(
        f"unknown effect {name!r}; the catalog has {sorted(CATALOG)}, injection only "
        f"{sorted(INJECTION_ONLY)}, outside the catalog {sorted(OUTSIDE_CATALOG)}"
    )


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

    ``effects`` is a list of (name, params): effects of :mod:`.effects` with their
    parameters (a scalar or one value per detector each; glitches as ``{"events":
    [(detector, time_s, amplitude_k, tau_s), ...]}``; noise_mismatch as ``{"net_ukrts",
    "fknee_mhz", "alpha"}``; pointing_offset / pointing_drift as ``{"offset_x",
    "offset_y", "drift_x", "drift_y"}`` [arcmin, arcmin/h], injected by rotating the
    detector quaternions while the recording keeps the nominal pointing;
    ``("tes_electrothermal", {"p0_w", "kelvin_per_watt", ...})``; a
    ``detector_time_constant`` with ``"through_noise": True`` filters the noise as well,
    the noise then rolls off: :mod:`.rolloff`). The noise comes from its own stream
    ``(master_seed, "noise", channel, noise_seed, 0, detector)``. The truth is kept in
    ``recording.injected`` (never written to a file).
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
    # each effect at its stage (INJECTION_STAGES); an unknown name stops before any work
    staged = [(injectable(name), params) for name, params in effects]
    staged = [(effect, params, effect.injection_stage(params)) for effect, params in staged]

    def at(stage):
        return [(effect, params) for effect, params, where in staged if where == stage]

    moves = [params for _, params in at("pointing")]
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

    for effect, params in at("signal"):
        signal = effect.apply(ctx, params, signal)
    noise_params = next((params for _, params in at("noise")), None)
    tod = signal + _noise(simulator, pointing, master_seed, noise_seed, noise_params)
    for stage in INJECTION_STAGES[INJECTION_STAGES.index("noise") + 1 :]:  # on signal + noise
        for effect, params in at(stage):
            tod = effect.apply(ctx, params, tod)

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
