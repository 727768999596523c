"""Recordings with a known truth, for the diagnosis tests and the rates benchmark
(``benchmarks/diagnose_benchmark.py``).

Recordings: one detector pair (M1-140 unless told), nside 32 CMB sky, the channel's
nominal A_2, P_0 and K/W computed from the default configuration (:func:`nominal`),
simulated with litebird_sim through ``simulate_recording``, written to HDF5 and read back
with ``read_recording`` before ``diagnose`` sees them. :func:`nominal_errors` draws the
ways a real recording differs from its nominal model (A_2, 2f phase, gain, polarisation
angle, offsets, noise, sky), :func:`recorded_with_errors` puts them in a recording. The
noise seed of every recording differs from any other; the diagnosis never sees it (its
nominal model has no noise).
"""

from __future__ import annotations

import functools

import numpy as np

from .. import sky
from ..config import default_config_path, load_config
from ..simulation.channel_inputs import channel_conversion
from .pipeline import diagnose
from .recording import read_recording, write_recording
from .simulate import injectable, simulate_recording

CHANNEL = "M1-140"
NSIDE = 32
MASTER_SEED = 20240617


@functools.lru_cache(maxsize=8)
def nominal(channel: str = CHANNEL) -> dict:
    """The channel's nominal values from the default configuration's optics (as the
    workflow's kw_conversion stage computes them): ``a2_k`` the HWPSS amplitude A_2
    [K_CMB], ``p0_w`` the optical load [W], ``kelvin_per_watt`` [K_CMB / W]."""
    row = channel_conversion(load_config(default_config_path()), channel)
    return {
        "a2_k": row["a2_k_cmb"],
        "p0_w": row["p_nominal_w"],
        "kelvin_per_watt": row["kelvin_per_watt"],
    }


_M1_140 = nominal()
A2_K = _M1_140["a2_k"]  # M1-140's HWPSS amplitude A_2 [K_CMB]
P0_W = _M1_140["p0_w"]  # M1-140's nominal optical load [W]
KELVIN_PER_WATT = _M1_140["kelvin_per_watt"]  # M1-140's K/W conversion [K_CMB / W]


@functools.lru_cache(maxsize=1)
def sky_map() -> np.ndarray:
    return sky.cmb_map(NSIDE, 3 * NSIDE - 1, 0.0, MASTER_SEED, 0, 30.8)


def recorded(tmp_path, effects, noise_seed: int, hours: float = 2.0, name: str = "rec.h5"):
    """Simulate, write to HDF5, read back: (recording read from the file, injected truth)."""
    recording = simulate_recording(
        CHANNEL, hours, MASTER_SEED, noise_seed, sky_map(), A2_K, effects
    )
    path = tmp_path / name
    write_recording(path, recording)
    return read_recording(path), recording.injected


def run(recording, **kwargs):
    """The diagnosis (:class:`.report.diagnosis.Diagnosis`) of ``recording`` against the nominal sky and A_2."""
    return diagnose(recording, sky_map(), A2_K, **kwargs)


def nominal_errors(rng: np.random.Generator, n_det: int = 2, scale: float = 1.0) -> dict:
    """Random nominal-model errors of realistic size (what a real recording differs by).

    A_2 off by a few %, 2f phase ~1 deg, gain ~1 %, polarisation angle ~0.5 deg, detector
    offsets ~mK, noise level ~10 % (and knee ~30 %), the supplied sky map rescaled by a
    few % with a small unknown residual. Drawn per recording; the diagnosis is told none.
    ``scale`` multiplies every spread (a robustness check: errors larger than expected).
    """
    return {
        "a2_relative": rng.normal(0.0, 0.03 * scale, n_det),
        "phase_deg": rng.normal(0.0, 1.0 * scale, n_det),
        "gain": rng.normal(0.0, 0.01 * scale, n_det),
        "pol_angle_deg": rng.normal(0.0, 0.5 * scale, n_det),
        "offset_k": rng.normal(0.0, 2e-3 * scale, n_det),
        "net_factor": 1.0 + rng.normal(0.0, 0.10 * scale, n_det),
        "fknee_factor": np.exp(rng.normal(0.0, 0.3 * scale, n_det)),
        "sky_scale": 1.0 + rng.normal(0.0, 0.05 * scale),
        "sky_residual": abs(rng.normal(0.0, 0.05 * scale)),
        "sky_seed": int(rng.integers(1, 2**31)),
    }


def error_effects(errors: dict, detectors: list[dict], a2_k: float) -> list:
    """The nominal errors as injected effects: 2f amplitude/phase about the nominal
    ``a2_k`` [K], gain, noise level."""
    a2_true = a2_k * (1.0 + errors["a2_relative"])
    phase = np.radians(errors["phase_deg"])
    # A_2 cos x + c2 cos x + s2 sin x = A_2 (1 + e) cos(x - phase)
    c2 = a2_true * np.cos(phase) - a2_k
    s2 = a2_true * np.sin(phase)
    net = [d["net_ukrts"] * f for d, f in zip(detectors, errors["net_factor"], strict=True)]
    fknee = [d["fknee_mhz"] * f for d, f in zip(detectors, errors["fknee_factor"], strict=True)]
    return [
        ("hwpss_harmonics", {"c2": c2, "s2": s2}),
        ("gain_drift", {"g0": errors["gain"]}),
        ("noise_mismatch", {"net_ukrts": net, "fknee_mhz": fknee}),
    ]


def supplied_sky(errors: dict) -> np.ndarray:
    """The sky map the diagnosis is given: the true one rescaled, plus a small residual."""
    other = sky.cmb_map(NSIDE, 3 * NSIDE - 1, 0.0, errors["sky_seed"], 0, 30.8)
    return errors["sky_scale"] * sky_map() + errors["sky_residual"] * other


def recorded_with_errors(
    tmp_path,
    effects,
    noise_seed: int,
    errors: dict,
    hours: float = 2.0,
    name: str = "rec.h5",
    channel: str = CHANNEL,
    a2_k: float | None = None,
):
    """Like :func:`recorded`, with the nominal ``errors`` in the recording (not in the model).

    The recording is simulated with the true A_2 (the nominal ``a2_k`` [K_CMB], default
    the channel's, :func:`nominal`, times 1 + the error), phase, gain, noise and
    polarisation angles; the file carries the nominal polarisation angles and the
    detector offsets. Diagnose it against the same nominal ``a2_k``.
    """
    from .simulate import _simulated_base

    a2_k = nominal(channel)["a2_k"] if a2_k is None else float(a2_k)

    simulator = _simulated_base(channel, float(hours), "2032-04-01T00:00:00", NSIDE)[0]
    detectors = [{"net_ukrts": d.net_ukrts, "fknee_mhz": d.fknee_mhz} for d in simulator.detectors]
    a2_true = a2_k * (1.0 + errors["a2_relative"])
    # an effect of the HWPSS acts on the recording's true HWPSS (Effect.on_true_hwpss)
    phase = np.radians(errors["phase_deg"])
    effects = [
        (name, injectable(name).on_true_hwpss(params, a2_true, a2_k, phase))
        for name, params in effects
    ]
    # the optical signal first (the true 2f HWPSS, then the effects), the detector's gain
    # error on all of it, then the noise
    a2_error, gain_error, noise_error = error_effects(errors, detectors, a2_k)
    recording = simulate_recording(
        channel,
        hours,
        MASTER_SEED,
        noise_seed,
        sky_map(),
        a2_k,
        [a2_error, *effects, gain_error, noise_error],
        pol_angle_offsets_rad=np.radians(errors["pol_angle_deg"]),
    )
    recording.tod += np.asarray(errors["offset_k"])[:, None]
    path = tmp_path / name
    write_recording(path, recording)
    return read_recording(path), recording.injected
