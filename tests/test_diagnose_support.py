"""Shared helpers of the diagnosis tests (no tests here).

Recordings: one MFT pair (M1-140), nside 32 CMB sky, A_2 = 0.264 K (the study's M1-140
value), simulated with litebird_sim through ``simulate_recording``, written to HDF5 and
read back with ``read_recording`` before ``diagnose`` sees them. The noise seed of every
recording differs from any other; the diagnosis never sees it (its nominal model has no
noise).
"""

from __future__ import annotations

import functools

import numpy as np

from hwp_tes_systematics import sky
from hwp_tes_systematics.diagnose import read_recording, simulate_recording, write_recording
from hwp_tes_systematics.diagnose.report import diagnose

CHANNEL = "M1-140"
NSIDE = 32
A2_K = 0.264  # M1-140 HWPSS amplitude [K_CMB] (results/inputs/kw_conversion.csv)
MASTER_SEED = 20240617
P0_W = 4.088479789e-13  # M1-140 nominal optical load [W] (results/inputs/tes_response.csv)
KELVIN_PER_WATT = 5.644925449e12  # M1-140 K/W conversion (results/inputs/kw_conversion.csv)


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


def run(recording, **kwargs) -> dict:
    return diagnose(recording, sky_map(), A2_K, **kwargs)


def parameter(result: dict, effect: str, name: str, detector: int) -> dict:
    """The {value, sigma, unit} of ``name`` for ``detector`` (index) in the result's effect."""
    for item in result["effects"]:
        if item["name"] != effect:
            continue
        for entry in item["parameters"].values():
            if (
                entry["parameter"] == name
                and entry["detector"] == result["recording"]["detectors"][detector]
            ):
                return entry
    raise KeyError(f"{effect}.{name}[{detector}] not in {[e['name'] for e in result['effects']]}")


def names(result: dict) -> list[str]:
    return [effect["name"] for effect in result["effects"]]
