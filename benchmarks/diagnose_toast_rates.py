"""Rates of the diagnosis on recordings TOAST 3 made (needs the ``toast`` extra).

    python benchmarks/diagnose_toast_rates.py --per-case 20 --out toast_rates.json
    python benchmarks/diagnose_toast_rates.py --only nonlinearity gain_drift --g1-range 1e-5 2e-3 \
        --drift-range 1e-4 3e-3 --first-seed 1001 --out toast_ladder.json   # to non-detection

Each recording is written by TOAST's operators (:mod:`hwp_tes_systematics.diagnose.toast_testbed`:
SimSatellite's LiteBIRD scan with a HWP, ScanHealpixMap, SimDipole, SimNoise, SaveHDF5)
and read back by the diagnosis as a user's file would be. Drawn per recording (never
tuned): a start in 2032-2034, a CMB sky realisation (nside 32), duration 1-3 h,
sampling rate 19 or 31 Hz, HWP 39, 46 or 61 rpm, A_2 0.1-0.4 K,
NET 30-80 uK sqrt(s), knee 10-50 mHz, one pixel (a pair) or, one recording in five,
seven (14 detectors), 2 % of the samples flagged in one recording in three, and the
nominal errors the diagnosis is not told: A_2 given 3 % off, a 2f phase of ~1 deg, a
gain ~1 %, the file's NET ~10 % off the noise drawn, the sky TOAST scans ~5 % brighter or
fainter than the map the diagnosis is given. Then one case:

* ``clean``: nothing more (a false alarm is any effect reported or structure left);
* ``nonlinearity``: d -> (1 + g1 d) d, |g1| log-uniform in 2e-3 - 3e-2 K^-1
  (``--g1-range``) with a random sign, before the gain error; expected ``tes_nonlinearity`` (or its cubic form) first,
  every detector's g1 within 3 sigma of g1 / (1 + gain) (g1 in the recorded units: the
  gain rescales the temperature axis, d_rec = d' + g1 d'^2 / (1 + gain), d' = (1 + gain) d);
* ``gain_drift``: TOAST's ``GainDrifter`` (linear_drift, sigma 3e-3 - 3e-2,
  ``--drift-range``): each detector
  a ramp 1 + s t / T; expected ``gain_drift`` first, its g1 (the P1 coefficient) within
  3 sigma of s / (2 + s);
* ``both``: the nonlinearity and the gain drift; expected both named, one of them first,
  g1 against g1 / ((1 + gain) (1 + s / 2)) (GainDrifter acts after the nonlinearity, as a
  readout gain would: in the recorded units g1 is divided by the ramp, whose mean the
  diagnosis's gain takes; the diagnosis composes the nonlinearity on the drifted signal,
  so the ramp's change of g1 over the recording, +-s/2, is left to the residual).

``--net-spread s``: each detector's NET drawn around the recording's, times 1 + s N(0, 1)
(the last draw, so the rest of a recording is the same without it; the truths of
crosstalk and the common noise follow each detector's NET).

``crosstalk``: TOAST's ``CrossTalk`` (after the noise: the readout's) with 1 coupling
(a pair) or 1-3 (14 detectors) between random detectors, |c_ij| 1e-2 - 5e-2
(``--crosstalk-range``), half of them with a coupling back of 0 - 1 times it; expected
``detector_crosstalk`` taking exactly the coupled pairs, x within 3 sigma of c_ij + c_ji.

The wafer cases (``--only clean_wafers wafer_drift detector_drift mixed_drift``): 14
detectors (seven pixels) on 2 or 3 wafers (a focal-plane ``wafer`` column), the rest
drawn as above, and TOAST's ``GainDrifter`` in ``slow_drift`` mode (a 1/f gain stream
below 0.2 mHz, sigma 1e-2 - 5e-2, ``--slow-range``; ``detector_mismatch`` m its part
per detector, 1 - m common to a wafer):

* ``clean_wafers``: no drift (false alarms);
* ``wafer_drift``: m = 0, expected ``gain_drift`` with scope ``wafer``;
* ``detector_drift``: m = 1, expected ``gain_drift`` with scope ``detector``;
* ``mixed_drift``: m in 0.2 - 0.5, expected ``gain_drift`` (its scope counted);

each g1 (a group's, or each detector's) against the P1 coefficient of the gain stream
over (1 + its P0) (the group's mean for a group).

``bath_fluctuation``: 14 detectors on 2 or 3 wafers, TOAST's ``GainDrifter`` in
``thermal_drift`` mode twice (a 1/f bath temperature up to Nyquist, fknee 20 mHz): a
stream common to each wafer or, half of the time, to all detectors, its sigma_drift
log-uniform in 1e-5 - 1e-4 K (``--thermal-range``), and a stream of each detector's own,
0.3 - 1.5 times it; expected ``gain_fluctuations`` first, its scope the groups of the
common stream and rho within 3 sigma of the common stream's share of the gain power
(a smooth drift named beside it is its slow part, counted as another effect).

``common_mode``: 14 detectors on 2 or 3 wafers, TOAST's ``CommonModeNoise`` (alpha 1,
knee 20 mHz, coupling 1) common to each wafer or, half of the time, to all detectors, its
NET 0.1 - 0.5 times the detectors' (``--common-range``), and in half of the recordings a
crosstalk coupling of 2 - 5 % in one pair beside it; expected ``common_mode_noise`` first,
its scope the common noise's groups, each b_i within 3 sigma of NET_c / sqrt(NET_i^2 +
NET_c^2), and the coupled pair (if any) as ``detector_crosstalk``.

``cosmic_rays`` (``--only cosmic_rays``): TOAST's ``InjectCosmicRays`` on a pair or
14 detectors: direct hits C1 + C2 exp(-t / tau) at 1 kHz, resampled by TOAST to the
recording's rate over 0.15 s (3 samples at 19 Hz, 5 at 31 Hz), 1e-3 - 5e-3 hits per second
per detector, C2 drawn over a decade above a level log-uniform in 3 - 300 times the white
noise per sample (``--hit-range``; the peak after resampling is what is scored), C1 up to
10 % of C2, tau 2 - 20 ms; and its white wafer noise, rms 0.1 - 0.5 times the detector
noise per sample, half the time with its pixel-pair common mode requested at 0.3 - 0.9
correlation (TOAST 3.0.6 draws the two detectors' "common" parts from different counters:
uncorrelated, < 0.01 measured, so it adds white noise only). Expected ``glitches`` first
and nothing else; the hits found (an event within 2 samples of a hit's first sample; a
hit on flagged samples is not in the recording and not scored) by the hit's peak over the
white noise per sample, the events found at no hit, and each
found hit's time against its first sample (sigma half a sample).

``coincident_rays``: the same, each detector of a wafer (of the recording, for a pair or
one wafer) given the hits TOAST drew for the wafer's first detector, times a factor of
0.3 - 1 drawn per detector (``cosmic_rays.shared`` of the testbed): coincident hits, the
coincidence made by the testbed, the hits by TOAST. Expected ``glitches`` scoped by
coincidence, and each hit that two or more detectors see above 10 times the white noise
per sample found as one coincident event; in ``cosmic_rays`` (independent hits) the scope
by coincidence is a false alarm.

``readout_steps``: steps on TOAST's TOD (signal and noise; TOAST has no step operator:
the testbed's ``readout_steps``), d -> d + H(t - t_s) (o + s d), in 1 - 3 detectors at
times drawn over 10 - 90 % of the recording, or, one recording in three, a bias line's
detectors at one time (a pair's two, 3-6 of 14 detectors); each step an offset, a gain
or both (a third each), |o| log-uniform in 0.1 - 3 times the white noise per sample and
|s| A_2 in 0.01 - 0.3 times it (``--step-range``, the two lower ends scaled together), random signs. Expected
``readout_steps`` first; each step found (a step of its detector within 60 s, or 3 of
its time's error where that is wider: a weak gain step's time is known to minutes), its time
and its injected parts within 3 sigma, by strength (the larger of |o| and |s| A_2 over
the white noise per sample); the steps found where none was; a step shared by 3-6
detectors scoped by coincidence (a pair's one shared step is short of 5 sigma: chance
expects ~1e-3 of it).

``bias_line_steps``: one step shared by a bias line of 14 detectors (7 pixels), 3-6 of
them at one time, as a change of the line's bias would make: the part (offset, gain or
both) and the signs drawn once for the line, the line's |o| and |s| A_2 log-uniform in
0.5 - 3 times the white noise per sample (``--bias-line-range``), each detector's times
1 + 0.2 N(0, 1) (its own responsivity). Scored as ``readout_steps``; expected besides:
the step scoped by coincidence, every detector of the line in the coincident event.

Prints one line per recording and, per case, the rates: per recording (every detector's
parameters within 3 sigma; a parameter without a sigma fails) and per parameter, the
pulls' standard deviation, and the rates by the effect's strength |truth| / sigma (the
weakest detector's: below 5, 5-20, above 20); ``--out`` keeps every record (fitted values
and truth), ``--combine`` prints the rates of several such files.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import shutil
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import healpy as hp
import numpy as np

from hwp_tes_systematics.diagnose import diagnose, read_recording
from hwp_tes_systematics.diagnose.recording_checks import RecordingError
from hwp_tes_systematics.diagnose.testbed import MASTER_SEED, NSIDE
from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording
from hwp_tes_systematics.sky import cmb_map

CASES = ("clean", "nonlinearity", "gain_drift", "both")
# 14 detectors on 2 or 3 wafers, TOAST's slow_drift: a 1/f gain stream below 0.2 mHz,
# detector_mismatch m its part per detector, 1 - m common to a wafer
WAFER_CASES = (
    "clean_wafers",
    "wafer_drift",
    "detector_drift",
    "mixed_drift",
    "crosstalk",
    "bath_fluctuation",
    "common_mode",
)
MISMATCH = {"wafer_drift": (0.0, 0.0), "detector_drift": (1.0, 1.0), "mixed_drift": (0.2, 0.5)}
EXPECTED_SCOPE = {"wafer_drift": "wafer", "detector_drift": "detector"}
# TOAST's InjectCosmicRays on a pair or 14 detectors: independent hits, or each wafer's
# (a pair's) hits shared by its detectors
RAY_CASES = ("cosmic_rays", "coincident_rays")
# readout steps (the testbed's, on TOAST's TOD): offsets and gains jumping at one time
# and one bias line's step, strong enough in every detector of the line to be seen
STEP_CASES = ("readout_steps", "bias_line_steps")
OTHER_CASES = (*RAY_CASES, *STEP_CASES)
NONLINEARITY_NAMES = ("tes_nonlinearity", "tes_nonlinearity_cubic")
START = datetime(2032, 1, 1, tzinfo=UTC)


def log_uniform(rng, bounds) -> float:
    return float(np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]))))


def draw(
    case: str,
    rng: np.random.Generator,
    g1_range,
    drift_range,
    slow_range,
    crosstalk_range=None,
    thermal_range=None,
    common_range=None,
    net_spread=0.0,
    hit_range=(3.0, 300.0),
    step_range=(0.1, 3.0),
    bias_line_range=(0.5, 3.0),
) -> dict:
    """The recording's set-up, nominal errors and injected effect."""
    a2_true = float(rng.uniform(0.1, 0.4))
    setup = {
        "start_day": int(rng.integers(0, 3 * 365)),  # days after 2032-01-01
        "hours": float(rng.uniform(1.0, 3.0)),
        "sample_rate_hz": float(rng.choice([19.0, 31.0])),
        "hwp_rpm": float(rng.choice([39.0, 46.0, 61.0])),
        "a2_k": a2_true,
        "hwpss_phase_rad": float(np.radians(rng.normal(0.0, 1.0))),
        "gain": float(rng.normal(0.0, 0.01)),
        "net_uk_rts": float(rng.uniform(30.0, 80.0)),
        "fknee_mhz": float(rng.uniform(10.0, 50.0)),
        "net_written_factor": float(1.0 + rng.normal(0.0, 0.1)),
        "n_pixels": 7 if rng.random() < 0.2 else 1,
        "flagged_fraction": 0.02 if rng.random() < 1 / 3 else 0.0,
    }
    if case in WAFER_CASES and case != "crosstalk":
        setup.update(n_pixels=7, wafers=int(rng.choice([2, 3])))
    if case == "crosstalk":  # 1-3 couplings c_ij, one direction or both
        n_det = 2 * setup["n_pixels"]
        couplings = {}
        for _ in range(1 if n_det == 2 else int(rng.integers(1, 4))):
            i, j = (int(k) for k in rng.choice(n_det, 2, replace=False))
            value = float(rng.choice([-1, 1])) * log_uniform(rng, crosstalk_range)
            couplings[f"{i},{j}"] = value
            if rng.random() < 0.5:
                couplings[f"{j},{i}"] = value * float(rng.uniform(0.0, 1.0))
        setup["crosstalk"] = couplings
    if case == "bath_fluctuation":  # a stream common to a wafer (or all), one per detector
        common = log_uniform(rng, thermal_range)
        setup["thermal_drift"] = [common, common * float(rng.uniform(0.3, 1.5))]
        setup["thermal_drift_common_to"] = str(rng.choice(["wafer", "all"]))
    if case == "common_mode":  # a noise common to each wafer (or all), a coupled pair
        net_common = float(np.mean(setup["net_uk_rts"])) * float(rng.uniform(*common_range))
        setup["common_mode"] = [net_common, 20.0, str(rng.choice(["wafer", "all"]))]
        if rng.random() < 0.5:
            i, j = (int(k) for k in rng.choice(14, 2, replace=False))
            setup["crosstalk"] = {f"{i},{j}": float(rng.uniform(0.02, 0.05))}
    if case == "coincident_rays" and setup["n_pixels"] > 1:  # hits shared by a wafer
        setup["wafers"] = int(rng.choice([1, 2]))
    if case in RAY_CASES:  # what cosmic_ray_injection makes the hits and noise of
        setup["cosmic_rays"] = {
            "event_rate_hz": log_uniform(rng, (1e-3, 5e-3)),
            "hit_level": log_uniform(rng, hit_range),  # C2's lower end / the white noise
            "hit_seed": int(rng.integers(1, 2**31)),
            "wafer_noise": float(rng.uniform(0.1, 0.5)),  # its rms / the white noise
            "pair_correlation": float(rng.uniform(0.3, 0.9)) if rng.random() < 0.5 else None,
        }
        if case == "coincident_rays":  # each detector's share of a hit: 0.3 - 1
            n_det = 2 * setup["n_pixels"]
            setup["cosmic_rays"]["shared_scale"] = rng.uniform(0.3, 1.0, n_det).tolist()
    if case == "readout_steps":
        setup["readout_steps"] = draw_steps(rng, 2 * setup["n_pixels"], step_range)
    if case == "bias_line_steps":
        setup["n_pixels"] = 7
        setup["readout_steps"] = draw_bias_line_step(rng, 14, bias_line_range)
    if case in MISMATCH:
        setup["gain_drift_mode"] = "slow_drift"
        setup["gain_drift_mismatch"] = float(rng.uniform(*MISMATCH[case]))
        setup["gain_drift_sigma"] = log_uniform(rng, slow_range)
    if case in ("nonlinearity", "both"):
        setup["g1_per_k"] = float(rng.choice([-1, 1])) * log_uniform(rng, g1_range)
    if case in ("gain_drift", "both"):
        setup["gain_drift_sigma"] = log_uniform(rng, drift_range)
    a2_told = a2_true * (1.0 + rng.normal(0.0, 0.03))
    sky = {"sky_seed": int(rng.integers(1, 2**31)), "sky_scale": float(1 + rng.normal(0, 0.05))}
    if net_spread:  # each detector its own NET (drawn last: the rest is unchanged)
        spread = 1 + net_spread * rng.normal(0.0, 1.0, 2 * setup["n_pixels"])
        setup["net_uk_rts"] = (setup["net_uk_rts"] * np.clip(spread, 0.5, 1.5)).tolist()
    return {"setup": setup, "a2_told_k": float(a2_told), **sky}


def draw_steps(rng: np.random.Generator, n_det: int, step_range) -> list[list]:
    """[detector, time fraction, offset / white noise, s A_2 / white noise] per step: 1-3
    detectors (one for a pair) at their own times or, one time in three, a bias line's
    detectors at one time (a pair's two, 3-6 of 14); each an offset, a gain or both."""
    if rng.random() < 1 / 3:
        count = 2 if n_det == 2 else int(rng.integers(3, 7))
        at = float(rng.uniform(0.1, 0.9))
        chosen = [(int(k), at) for k in rng.choice(n_det, count, False)]
    else:
        count = 1 if n_det == 2 else int(rng.integers(1, 4))
        chosen = [(int(k), float(rng.uniform(0.1, 0.9))) for k in rng.choice(n_det, count, False)]
    steps = []
    for detector, at in chosen:
        part = str(rng.choice(["offset", "gain", "both"]))
        offset = float(rng.choice([-1, 1])) * log_uniform(rng, step_range)
        gain = float(rng.choice([-1, 1])) * log_uniform(rng, np.asarray(step_range) * 0.1)
        steps.append(
            [detector, at, offset if part != "gain" else 0.0, gain if part != "offset" else 0.0]
        )
    return steps


BIAS_LINE_SCATTER = 0.2  # the rms of a line's detectors' step about the line's


def draw_bias_line_step(rng: np.random.Generator, n_det: int, strength_range) -> list[list]:
    """[detector, time fraction, offset / white noise, s A_2 / white noise] for 3-6 of
    ``n_det`` detectors stepping at one time: the part and the signs drawn once, the
    line's |o| and |s| A_2 log-uniform over ``strength_range`` times the white noise,
    each detector's 1 + BIAS_LINE_SCATTER N(0, 1) times the line's (floored at 0.3)."""
    chosen = rng.choice(n_det, int(rng.integers(3, 7)), replace=False)
    at = float(rng.uniform(0.1, 0.9))
    part = str(rng.choice(["offset", "gain", "both"]))
    offset = float(rng.choice([-1, 1])) * log_uniform(rng, strength_range)
    gain = float(rng.choice([-1, 1])) * log_uniform(rng, strength_range)
    steps = []
    for detector in chosen:
        own = max(0.3, 1.0 + BIAS_LINE_SCATTER * float(rng.normal()))
        steps.append(
            [
                int(detector),
                at,
                own * offset if part != "gain" else 0.0,
                own * gain if part != "offset" else 0.0,
            ]
        )
    return steps


def step_injection(setup: dict) -> list[list]:
    """The testbed's ``readout_steps`` from a drawn set-up: [detector, first sample, o [K],
    s] (the amplitudes drawn over the white noise per sample)."""
    sigma = white_noise_k(setup)
    n = int(setup["hours"] * 3600 * setup["sample_rate_hz"])
    return [
        [detector, int(at * n), offset * sigma, gain * sigma / setup["a2_k"]]
        for detector, at, offset, gain in setup["readout_steps"]
    ]


def detector_nets(setup: dict, n_det: int) -> np.ndarray:
    """Each detector's NET [uK sqrt(s)] of a drawn set-up."""
    return np.broadcast_to(np.asarray(setup["net_uk_rts"], dtype=float), (n_det,))


def white_noise_k(setup: dict) -> float:
    """The detectors' white noise per sample [K]: TOAST's NET sqrt(f_s)."""
    return float(np.mean(setup["net_uk_rts"])) * 1e-6 * math.sqrt(setup["sample_rate_hz"])


def cosmic_ray_injection(setup: dict, n_draws: int = 400) -> dict:
    """The ``cosmic_rays`` argument of :func:`write_toast_recording` from a drawn set-up:
    ``n_draws`` hits for TOAST to resample, C2 log-uniform over a decade above the level,
    C1 up to 10 % of C2, tau 2 - 20 ms."""
    rays, sigma = setup["cosmic_rays"], white_noise_k(setup)
    rng = np.random.default_rng(rays["hit_seed"])
    c2 = rays["hit_level"] * sigma * np.exp(rng.uniform(0.0, math.log(10.0), n_draws))
    return {
        "event_rate_hz": rays["event_rate_hz"],
        "hits": {
            "c1": c2 * rng.uniform(0.0, 0.1, n_draws),
            "c2": c2,
            "tau_ms": rng.uniform(2.0, 20.0, n_draws),
        },
        "wafer_noise_k": [0.0, rays["wafer_noise"] * sigma],
        "pair_correlation": rays["pair_correlation"],
    } | (
        {
            "shared": {
                "by": "wafer" if setup.get("wafers", 1) > 1 else "all",
                "scale": rays["shared_scale"],
            }
        }
        if "shared_scale" in rays
        else {}
    )


def within(parameters: dict, name: str, truth: dict) -> tuple[list[float], float]:
    """Pulls (value - truth) / sigma of ``name`` per detector (inf without a sigma: a
    failure; a parameter shared by the detectors, ``common``, against their mean truth),
    and the weakest detector's strength |truth| / sigma."""
    rows = [p for p in parameters.values() if p["parameter"] == name]
    truth = {**truth, "common": float(np.mean(list(truth.values())))}  # a shared fit's
    pulls = [
        (p["value"] - truth[p["detector"]]) / p["sigma"] if p.get("sigma") else math.inf
        for p in rows
    ]
    strengths = [abs(truth[p["detector"]]) / p["sigma"] for p in rows if p.get("sigma")]
    return pulls, min(strengths, default=math.nan)


def fitted(parameters: dict, name: str) -> dict:
    """{detector: [value, sigma]} of ``name``."""
    return {
        p["detector"]: [p["value"], p.get("sigma")]
        for p in parameters.values()
        if p["parameter"] == name
    }


def score_wafer(case: str, result: dict, truth: dict) -> dict:
    """A slow drift on wafers: gain_drift named, its scope, each detector's (or group's)
    g1 against the stream's P1 coefficient over (1 + P0) (the nominal gain takes P0)."""
    effects = result["effects"]
    record = {"reported": [e["name"] for e in effects], "unexplained": len(result["unexplained"])}
    match = [effect for effect in effects if effect["name"] == "gain_drift"]
    record["named"] = bool(match)
    # named as the look-alike the report says it cannot tell from the effect it names
    record["look_alike"] = any("gain_drift" in effect["look_alikes"] for effect in effects)
    record["first"] = bool(effects) and effects[0]["name"] == "gain_drift"
    record["pulls"] = []
    record["within_3_sigma"] = False
    if not match:
        return record
    scope = match[0]["scope"]
    record["scope"] = scope["by"]
    g1 = {
        name: truth["gain_drift_legendre"][name][0] / (1 + truth["gain_drift_mean"][name])
        for name in truth["detectors"]
    }
    groups = {f"{scope['by']} {label}": members for label, members in scope["groups"].items()}
    for group, members in groups.items():  # a group's truth: its detectors' mean
        g1[group] = float(np.mean([g1[name] for name in members]))
    parameters = match[0]["parameters"]
    if groups:  # the groups' values only (each detector's is its group's)
        parameters = {k: p for k, p in parameters.items() if p["detector"] in groups}
    pulls, strength = within(parameters, "g1", g1)
    record["gain_drift_fitted"] = fitted(parameters, "g1")
    record["gain_drift_strength"] = round(strength, 2)
    record["pulls"] = [round(p, 2) for p in pulls]
    record["within_3_sigma"] = all(abs(p) < 3 for p in pulls)
    return record


def score_fluctuation(result: dict, setup: dict) -> dict:
    """A bath temperature: gain_fluctuations named, its scope, rho against the common
    stream's share of the gain power."""
    effects = result["effects"]
    record = {"reported": [e["name"] for e in effects], "unexplained": len(result["unexplained"])}
    match = [e for e in effects if e["name"] == "gain_fluctuations"]
    record["named"] = bool(match)
    record["first"] = bool(effects) and effects[0]["name"] == "gain_fluctuations"
    record["scope_expected"] = setup["thermal_drift_common_to"]
    record["pulls"], record["within_3_sigma"] = [], False
    if not match:
        return record
    record["scope"] = match[0]["scope"]["by"]
    common, own = setup["thermal_drift"]
    rho = match[0]["parameters"]["rho[common]"]
    expected = common**2 / (common**2 + own**2)
    record["rho_fitted"], record["rho_expected"] = [rho["value"], rho["sigma"]], expected
    pulls, strength = within({"rho": rho}, "rho", {"common": expected})
    record["rho_strength"] = round(strength, 2)
    record["pulls"] = [round(p, 2) for p in pulls]
    record["within_3_sigma"] = all(abs(p) < 3 for p in pulls)
    return record


def score_common_mode(result: dict, setup: dict, truth: dict) -> dict:
    """TOAST's CommonModeNoise: common_mode_noise named, its scope, each b_i against its
    truth (:func:`common_mode_pulls`); a coupled pair beside it named as crosstalk."""
    effects = result["effects"]
    record = {"reported": [e["name"] for e in effects], "unexplained": len(result["unexplained"])}
    match = [e for e in effects if e["name"] == "common_mode_noise"]
    crosstalk = [e for e in effects if e["name"] == "detector_crosstalk"]
    record["crosstalk_named"] = bool(crosstalk) == bool(setup.get("crosstalk"))
    record["named"] = bool(match) and record["crosstalk_named"]
    record["first"] = bool(effects) and effects[0]["name"] == "common_mode_noise"
    record["scope_expected"] = setup["common_mode"][2]
    record["pulls"], record["within_3_sigma"] = [], False
    if not match:
        return record
    record["scope"] = match[0]["scope"]["by"]
    record["b_fitted"] = {
        p["detector"]: [p["value"], p["sigma"]] for p in match[0]["parameters"].values()
    }
    return {**record, **common_mode_pulls({**record, "setup": setup, "truth": truth})}


def common_mode_pulls(record: dict) -> dict:
    """Each fitted |b_i| against a_i NET_c / sqrt(NET_i^2 + a_i^2 NET_c^2), a_i = 1 +
    sum_j c_ij the detector's coupling to the common noise (its own, 1, and what a
    crosstalk leaks from its partners, who carry the same noise): pulls, the weakest
    strength, within 3 sigma. From the record alone (``--combine`` scores old records
    with it)."""
    setup, names = record["setup"], record["truth"]["detectors"]
    net_common = setup["common_mode"][0]
    nets = detector_nets(setup, len(names))
    coupling = np.ones(len(names))
    for key, value in setup.get("crosstalk", {}).items():
        coupling[int(key.split(",")[0])] += value
    expected = {
        name: a * net_common / math.hypot(net, a * net_common)
        for name, net, a in zip(names, nets, coupling, strict=True)
    }
    fitted = {
        name: {"value": abs(v), "sigma": s, "detector": name, "parameter": "b"}
        for name, (v, s) in record["b_fitted"].items()
    }
    pulls, strength = within(fitted, "b", {name: expected[name] for name in fitted})
    return {
        "b_expected": expected,
        "b_strength": round(strength, 2),
        "pulls": [round(p, 2) for p in pulls],
        "within_3_sigma": all(abs(p) < 3 for p in pulls),
    }


def coupled_pairs(setup: dict, names) -> dict[str, float]:
    """{"<name_i>-<name_j>" (i < j): x_ij} of the couplings drawn: d_i += c_ij d_j adds
    c_ij NET_j / NET_i to the pair's x."""
    nets = detector_nets(setup, len(names))
    x: dict[str, float] = {}
    for key, value in setup["crosstalk"].items():
        i, j = (int(k) for k in key.split(","))
        pair = f"{names[min(i, j)]}-{names[max(i, j)]}"
        x[pair] = x.get(pair, 0.0) + value * nets[j] / nets[i]
    return x


def score_crosstalk(result: dict, setup: dict, truth: dict) -> dict:
    """TOAST's CrossTalk: detector_crosstalk named, the pairs it takes against the pairs
    coupled, x_ij against c_ij NET_j / NET_i + c_ji NET_i / NET_j for each pair coupled."""
    effects = result["effects"]
    record = {"reported": [e["name"] for e in effects], "unexplained": len(result["unexplained"])}
    coupled = coupled_pairs(setup, truth["detectors"])
    match = [e for e in effects if e["name"] == "detector_crosstalk"]
    record["named"] = bool(match)
    record["first"] = bool(effects) and effects[0]["name"] == "detector_crosstalk"
    record["pulls"], record["within_3_sigma"] = [], False
    record["pairs_missed"], record["pairs_false"] = sorted(coupled), []
    if not match:
        return record
    parameters = match[0]["parameters"]
    taken = {p["detector"] for p in parameters.values() if p.get("taken")}
    record["pairs_missed"] = sorted(set(coupled) - taken)
    record["pairs_false"] = sorted(taken - set(coupled))
    pulls = [
        (parameters[f"x[{pair}]"]["value"] - value) / parameters[f"x[{pair}]"]["sigma"]
        for pair, value in coupled.items()
    ]
    strengths = [abs(v) / parameters[f"x[{p}]"]["sigma"] for p, v in coupled.items()]
    record["crosstalk_strength"] = round(min(strengths), 2)
    record["crosstalk_fitted"] = {
        p: [parameters[f"x[{p}]"]["value"], parameters[f"x[{p}]"]["sigma"]] for p in coupled
    }
    record["pulls"] = [round(p, 2) for p in pulls]
    record["within_3_sigma"] = all(abs(p) < 3 for p in pulls)
    return record


def score_cosmic_rays(result: dict, setup: dict, truth: dict) -> dict:
    """TOAST's direct hits: glitches named (first, alone), each hit found or not with its
    strength (peak over the white noise per sample, the wafer noise included), the events
    found at no hit, the found hits' time pulls (sigma half a sample)."""
    effects = result["effects"]
    names = [e["name"] for e in effects]
    record = {"reported": names, "unexplained": len(result["unexplained"])}
    record["named"] = "glitches" in names
    record["first"] = bool(names) and names[0] == "glitches"
    fs = setup["sample_rate_hz"]
    rays = setup["cosmic_rays"]
    sigma = white_noise_k(setup) * math.sqrt(
        1 + rays["wafer_noise"] ** 2 * (1 + (rays["pair_correlation"] or 0.0))
    )
    events: dict[str, list[float]] = {name: [] for name in truth["detectors"]}
    for effect in effects:
        if effect["name"] == "glitches":
            for p in effect["parameters"].values():
                if p["parameter"] == "time":
                    events[p["detector"]].append(p["value"])
    hits, pulls, false_events = [], [], 0
    for name in truth["detectors"]:
        starts = np.array([first / fs for first, _, _ in truth["cosmic_ray_hits"][name]])
        found = np.array(events[name])
        for (first, _, peak), start in zip(truth["cosmic_ray_hits"][name], starts, strict=True):
            near = found[np.abs(found - start) <= 2.0 / fs] if found.size else found
            hits.append([round(abs(peak) / sigma, 2), bool(near.size)])
            if near.size:
                pulls.append(round(float((near[0] - start) / (0.5 / fs)), 2))
        false_events += int(
            sum(not starts.size or np.abs(starts - t).min() > 2.0 / fs for t in found)
        )
    record["hits"] = hits
    record["false_events"] = false_events
    record["pulls"] = pulls
    record["within_3_sigma"] = record["named"] and all(abs(p) < 3 for p in pulls)
    record.update(score_coincidences(effects, truth, fs, sigma))
    return record


SHARED_HIT_SIGMA = 10.0  # a shared hit is scored where two detectors see it above this


def score_coincidences(effects, truth: dict, fs: float, sigma: float) -> dict:
    """The glitches' scope by coincidence or not, and each hit that two or more detectors
    share above SHARED_HIT_SIGMA times the white noise per sample found as one coincident
    event (a group of the scope within 2 samples holding two of those detectors)."""
    scope = next((e["scope"] for e in effects if e["name"] == "glitches"), {"by": "none"})
    groups = [
        (float(label.split()[2]), set(names)) for label, names in scope.get("groups", {}).items()
    ]
    seen_by: dict[int, set] = {}
    for name, hits in truth["cosmic_ray_hits"].items():
        for first, _, peak in hits:
            if abs(peak) > SHARED_HIT_SIGMA * sigma:
                seen_by.setdefault(first, set()).add(name)
    shared = {first: names for first, names in seen_by.items() if len(names) >= 2}
    found = sum(
        any(abs(t - first / fs) <= 2.0 / fs and len(names & members) >= 2 for t, members in groups)
        for first, names in shared.items()
    )
    return {
        "coincidence_scope": scope["by"] == "coincidence",
        "shared_hits": len(shared),
        "shared_hits_found": int(found),
    }


STEP_WINDOW_S = 60.0  # a found step of the detector this close to an injected one is it


def score_steps(result: dict, setup: dict, truth: dict) -> dict:
    """Readout steps: named (first, alone), each injected step found or not with its
    strength, the pulls of its time and injected parts, the steps found at none, and the
    scope by coincidence of a pixel's shared step."""
    effects = result["effects"]
    names = [e["name"] for e in effects]
    record = {"reported": names, "unexplained": len(result["unexplained"])}
    record["named"] = "readout_steps" in names
    record["first"] = bool(names) and names[0] == "readout_steps"
    fs, sigma = setup["sample_rate_hz"], white_noise_k(setup)
    found: dict[str, dict[int, dict]] = {}  # detector -> step index -> its parameters
    scope = {"by": "none"}
    for effect in effects:
        if effect["name"] == "readout_steps":
            scope = effect["scope"]
            for key, p in effect["parameters"].items():
                index = int(key.split(".")[0][len("step") :])
                found.setdefault(p["detector"], {}).setdefault(index, {})[p["parameter"]] = p
    steps, matched = [], set()
    for name, injected in truth.get("readout_steps", {}).items():
        for first, offset, gain in injected:
            strength = max(abs(offset), abs(gain) * setup["a2_k"]) / sigma
            candidates = [  # within the window, or 3 of its time's error if wider
                (abs(p["time"]["value"] - first / fs), index, p)
                for index, p in found.get(name, {}).items()
                if abs(p["time"]["value"] - first / fs)
                <= max(STEP_WINDOW_S, 3 * p["time"]["sigma"])
            ]
            if not candidates:
                steps.append([round(strength, 3), False, []])
                continue
            _, index, p = min(candidates, key=lambda c: c[0])
            matched.add((name, index))
            pulls = [(p["time"]["value"] - first / fs) / p["time"]["sigma"]]
            for part, value in (("offset", offset), ("gain", gain)):
                if value != 0.0 or part in p:
                    entry = p.get(part)
                    pulls.append((entry["value"] - value) / entry["sigma"] if entry else math.inf)
            steps.append([round(strength, 3), True, [round(x, 2) for x in pulls]])
    record["steps"] = steps
    record["false_steps"] = sum(
        (name, index) not in matched for name, per in found.items() for index in per
    )
    pulls = [x for _, ok, ps in steps if ok for x in ps]
    record["pulls"] = pulls
    record["within_3_sigma"] = record["named"] and all(abs(x) < 3 for x in pulls)
    firsts = [first for per in truth.get("readout_steps", {}).values() for first, *_ in per]
    record["shared_step"] = max((firsts.count(f) for f in firsts), default=0)  # detectors
    record["coincidence_scope"] = scope["by"] == "coincidence"
    if record["shared_step"] >= 2:  # the detectors of the step most of them share
        line_first = max(firsts, key=firsts.count)
        line = {
            name
            for name, per in truth["readout_steps"].items()
            if any(first == line_first for first, *_ in per)
        }
        groups = scope.get("groups", {}).values() if record["coincidence_scope"] else []
        record["line_in_one_event"] = any(line <= set(members) for members in groups)
    return record


def score(case: str, result: dict, setup: dict, truth: dict) -> dict:
    effects = result["effects"]
    names = [effect["name"] for effect in effects]
    record = {"reported": names, "unexplained": len(result.get("unexplained", []))}
    if case in ("clean", "clean_wafers"):
        record["false_alarm"] = bool(names or record["unexplained"])
        return record
    if case in MISMATCH:
        return score_wafer(case, result, truth)
    if case == "crosstalk":
        return score_crosstalk(result, setup, truth)
    if case == "bath_fluctuation":
        return score_fluctuation(result, setup)
    if case == "common_mode":
        return score_common_mode(result, setup, truth)
    if case in RAY_CASES:
        return score_cosmic_rays(result, setup, truth)
    if case in STEP_CASES:
        return score_steps(result, setup, truth)
    expected = []
    if case in ("nonlinearity", "both"):
        expected.append("nonlinearity")
    if case in ("gain_drift", "both"):
        expected.append("gain_drift")
    found = {}
    for label in expected:
        wanted = NONLINEARITY_NAMES if label == "nonlinearity" else ("gain_drift",)
        match = [effect for effect in effects if effect["name"] in wanted]
        if not match:
            found[label] = None
            continue
        record[f"{label}_fitted"] = fitted(match[0]["parameters"], "g1")
        if label == "nonlinearity":
            slopes = truth.get("gain_drift_slope", dict.fromkeys(truth["detectors"], 0.0))
            g1 = {
                k: setup["g1_per_k"] / ((1 + setup["gain"]) * (1 + s / 2))
                for k, s in slopes.items()
            }
            pulls, strength = within(match[0]["parameters"], "g1", g1)
        else:
            slopes = truth["gain_drift_slope"]
            pulls, strength = within(
                match[0]["parameters"], "g1", {k: s / (2 + s) for k, s in slopes.items()}
            )
        found[label] = pulls
        record[f"{label}_strength"] = round(strength, 2)
    record["named"] = all(found[label] is not None for label in expected)
    allowed = {"nonlinearity": NONLINEARITY_NAMES, "gain_drift": ("gain_drift",)}
    record["first"] = bool(names) and any(names[0] in allowed[label] for label in expected)
    pulls = [p for label in expected for p in (found[label] or [])]
    record["pulls"] = [round(p, 2) for p in pulls]
    record["within_3_sigma"] = record["named"] and all(abs(p) < 3 for p in pulls)
    return record


def one(case: str, seed: int, folder: Path, ranges: tuple) -> dict:
    """Draw, write with TOAST, read and diagnose one recording; its record. ``ranges``:
    those of g1, the linear drift, the slow drift, the crosstalk, the bath's stream and
    the common noise."""
    rng = np.random.default_rng([seed, (CASES + WAFER_CASES + OTHER_CASES).index(case)])
    drawn = draw(case, rng, *ranges)
    sky = cmb_map(NSIDE, 3 * NSIDE - 1, 0.0, MASTER_SEED, drawn["sky_seed"], 30.8)
    folder.mkdir(parents=True)
    sky_fits = folder / "sky.fits"  # what TOAST scans: the sky the diagnosis is given, rescaled
    hp.write_map(sky_fits, drawn["sky_scale"] * sky, dtype=np.float64)
    start_time = START + timedelta(days=drawn["setup"]["start_day"])
    setup = {key: value for key, value in drawn["setup"].items() if key != "start_day"}
    if "crosstalk" in setup:  # drawn as "i,j" keys (JSON), given as (i, j)
        setup["crosstalk"] = {
            tuple(int(k) for k in key.split(",")): v for key, v in setup["crosstalk"].items()
        }
    if "cosmic_rays" in setup:
        setup["cosmic_rays"] = cosmic_ray_injection(setup)
    if "readout_steps" in setup:
        setup["readout_steps"] = step_injection(setup)
    truth: dict = {}
    path = write_toast_recording(
        folder, sky_fits, seed=seed, truth=truth, start=start_time, **setup
    )
    recording = read_recording(path)
    truth["detectors"] = recording.detector_names
    if "cosmic_ray_hits" in truth:  # a hit in flagged samples is not in the recording
        truth["cosmic_ray_hits_flagged"] = {}
        for k, name in enumerate(truth["detectors"]):
            hits = truth["cosmic_ray_hits"][name]
            seen = [not recording.flags[k, first : first + n].any() for first, n, _ in hits]
            truth["cosmic_ray_hits"][name] = [h for h, s in zip(hits, seen, strict=True) if s]
            truth["cosmic_ray_hits_flagged"][name] = [
                h for h, s in zip(hits, seen, strict=True) if not s
            ]
    start = time.monotonic()
    result = diagnose(recording, sky, drawn["a2_told_k"], figures=False).to_dict()
    record = {"case": case, "seed": seed, **drawn, "seconds": round(time.monotonic() - start, 1)}
    record["truth"] = truth
    record.update(score(case, result, drawn["setup"], truth))
    shutil.rmtree(folder)
    return record


def when_memory_allows(case: str, seed: int, folder: Path, ranges: tuple, tries: int = 30):
    """:func:`one`, tried again a minute later while the diagnosis refuses the recording
    for the memory available (another job on the machine holds it)."""
    for attempt in range(tries):
        try:
            return one(case, seed, folder, ranges)
        except RecordingError as error:
            if "available" not in str(error) or attempt == tries - 1:
                raise
            print(f"{case} {seed}: waiting for memory ({error})", file=sys.stderr, flush=True)
            shutil.rmtree(folder, ignore_errors=True)
            time.sleep(60)
    raise AssertionError("unreachable")


def summary(records: list[dict]) -> list[str]:
    lines = []
    for case in CASES + WAFER_CASES + OTHER_CASES:
        rows = [r for r in records if r["case"] == case]
        if not rows:
            continue
        n = len(rows)
        if case in RAY_CASES:
            lines += cosmic_ray_summary(case, rows)
        elif case in STEP_CASES:
            lines += step_summary(case, rows)
        elif case in ("clean", "clean_wafers"):
            alarms = sum(r["false_alarm"] for r in rows)
            lines.append(f"{case:13s} {n:3d} recordings: false alarms {alarms}/{n}")
        else:
            first = sum(r["first"] for r in rows)
            named = sum(r["named"] for r in rows)
            inside = sum(r["within_3_sigma"] for r in rows)
            pulls = [p for r in rows for p in r["pulls"]]
            inside_p = sum(abs(p) < 3 for p in pulls)
            extra = sum(len(r["reported"]) > (2 if case == "both" else 1) for r in rows)
            finite = [p for p in pulls if math.isfinite(p)]
            lines.append(
                f"{case:13s} {n:3d} recordings: ranked first {first}/{n}, every effect named "
                f"{named}/{n}, another effect named too {extra}/{n}; parameters within 3 "
                f"sigma: every one of the recording {inside}/{n}, "
                f"per parameter {inside_p}/{len(pulls)}; pulls' sd {np.std(finite):.2f}"
            )
            lines += by_amplitude(case, rows)
            if case in ("bath_fluctuation", "common_mode"):
                right = sum(r.get("scope") == r["scope_expected"] for r in rows)
                lines.append(f"    scope the common part's groups: {right}/{n}")
            if case == "common_mode":
                right = sum(r["crosstalk_named"] for r in rows)
                coupled = sum(bool(r["setup"].get("crosstalk")) for r in rows)
                lines.append(
                    f"    crosstalk named where a pair was coupled ({coupled}) and only there: "
                    f"{right}/{n}"
                )
            if case in MISMATCH:
                if all("look_alike" in r for r in rows):  # (records made before it: not)
                    alike = sum(not r["named"] and r["look_alike"] for r in rows)
                    lines.append(f"    not named but the look-alike of what was: {alike}")
                scopes = [r.get("scope", "none") for r in rows]
                counts = ", ".join(f"{k} {scopes.count(k)}" for k in sorted(set(scopes)))
                right = sum(s == EXPECTED_SCOPE.get(case) for s in scopes)
                lines.append(
                    f"    scope: {counts}"
                    + (
                        f" (expected {EXPECTED_SCOPE[case]}: {right}/{n})"
                        if case in EXPECTED_SCOPE
                        else ""
                    )
                )
    seconds = [r["seconds"] for r in records]
    lines.append(
        f"diagnosis time per recording: median {np.median(seconds):.1f} s, max {max(seconds):.1f} s"
    )
    return lines


HIT_STRENGTHS = (0.0, 5.0, 10.0, 20.0, math.inf)  # a hit's peak / the white noise per sample


def cosmic_ray_summary(case: str, rows: list[dict]) -> list[str]:
    """A cosmic-ray case: glitches ranked first and alone, the hits found by strength,
    the events found at no hit, the time pulls; the glitches scoped by coincidence, and
    the shared hits found as coincident events."""
    n = len(rows)
    first = sum(r["first"] for r in rows)
    alone = sum(r["reported"] == ["glitches"] and not r["unexplained"] for r in rows)
    others = sorted({name for r in rows for name in r["reported"] if name != "glitches"})
    hits = np.array([h for r in rows for h in r["hits"]], dtype=float).reshape(-1, 2)
    bins = []
    for low, high in itertools.pairwise(HIT_STRENGTHS):
        inside = hits[(hits[:, 0] >= low) & (hits[:, 0] < high)]
        bins.append(f"{low:g}-{high:g}: {int(inside[:, 1].sum())}/{len(inside)}")
    pulls = [p for r in rows for p in r["pulls"]]
    inside_p = sum(abs(p) < 3 for p in pulls)
    coincident = [r for r in rows if "coincidence_scope" in r]  # (not in older records)
    scoped = sum(r["coincidence_scope"] for r in coincident)
    shared = sum(r["shared_hits"] for r in coincident)
    shared_found = sum(r["shared_hits_found"] for r in coincident)
    return [
        (
            f"{case:15s} {n:3d} recordings: ranked first {first}/{n}, glitches alone (nothing "
            f"else, nothing unexplained) {alone}/{n}; also named: {', '.join(others) or 'none'}"
        ),
        "    hits found by peak / white noise per sample: " + ", ".join(bins),
        (
            f"    events found at no hit: {sum(r['false_events'] for r in rows)} in {n} "
            f"recordings; hit times within 3 sigma (half a sample): {inside_p}/{len(pulls)}"
        ),
        (
            f"    glitches scoped by coincidence: {scoped}/{len(coincident)}; hits shared by "
            f"two or more detectors above {SHARED_HIT_SIGMA:g} sigma found as one coincident "
            f"event: {shared_found}/{shared}"
        ),
    ]


STEP_STRENGTHS = (0.0, 0.1, 0.3, 1.0, math.inf)  # a step's |o| or |s| A_2 / white noise


def step_summary(case: str, rows: list[dict]) -> list[str]:
    """Readout steps: ranked first and alone, the steps found by strength, the pulls, the
    steps found at none, the shared steps scoped by coincidence."""
    n = len(rows)
    first = sum(r["first"] for r in rows)
    alone = sum(r["reported"] == ["readout_steps"] and not r["unexplained"] for r in rows)
    others = sorted({name for r in rows for name in r["reported"] if name != "readout_steps"})
    steps = [step for r in rows for step in r["steps"]]
    bins = []
    for low, high in itertools.pairwise(STEP_STRENGTHS):
        inside = [ok for strength, ok, _ in steps if low <= strength < high]
        bins.append(f"{low:g}-{high:g}: {sum(inside)}/{len(inside)}")
    pulls = [x for r in rows for x in r["pulls"]]
    shared = [r for r in rows if r["shared_step"] >= 3]
    in_one = sum(r.get("line_in_one_event", False) for r in shared)
    pairs = [r for r in rows if r["shared_step"] == 2]
    return [
        (
            f"{case:15s} {n:3d} recordings: ranked first {first}/{n}, alone (nothing "
            f"else, nothing unexplained) {alone}/{n}; also named: {', '.join(others) or 'none'}"
        ),
        "    steps found by |o| or |s| A_2 / white noise per sample: " + ", ".join(bins),
        (
            f"    time and parts within 3 sigma: {sum(abs(x) < 3 for x in pulls)}/{len(pulls)}; "
            f"steps found at none: {sum(r['false_steps'] for r in rows)} in {n} recordings"
        ),
        (
            f"    a step shared by 3-6 detectors scoped by coincidence: "
            f"{sum(r['coincidence_scope'] for r in shared)}/{len(shared)}; by a pair (one "
            f"coincidence, short of 5 sigma): {sum(r['coincidence_scope'] for r in pairs)}/"
            f"{len(pairs)}; unshared steps scoped by coincidence: "
            f"{sum(r['coincidence_scope'] for r in rows if r['shared_step'] < 2)}"
        ),
        f"    every detector of the shared step in one coincident event: {in_one}/{len(shared)}",
    ]


def by_amplitude(case: str, rows: list[dict]) -> list[str]:
    """Per decade of the drawn amplitude (g1 [1/K], or the drift's sigma): named / drawn,
    and within 3 sigma / named."""
    if case == "crosstalk":  # its pairs: the ones missed and the ones taken uncoupled
        missed = sum(  # (a recording not named: all its pairs)
            len(r.get("pairs_missed", []))
            if r["named"]
            else len({tuple(sorted(k.split(","))) for k in r["setup"]["crosstalk"]})
            for r in rows
        )
        false = sum(len(r.get("pairs_false", [])) for r in rows)
        coupled = sum(
            len({tuple(sorted(k.split(","))) for k in r["setup"]["crosstalk"]}) for r in rows
        )
        found, lost = [], []  # the pairs' expected |x| / sigma
        for r in rows:
            for pair, strength in expected_strengths(r).items():
                gone = not r["named"] or pair in r.get("pairs_missed", [])
                (lost if gone else found).append(strength)
        return [
            f"    pairs coupled {coupled}: missed {missed}, taken uncoupled {false}",
            (
                "    expected |x| / sigma (x from c and the NETs, sigma = 1 / sqrt(2 M), M the "
                f"modes above 1 Hz): found {_range(found)}, missed {_range(lost)}"
            ),
        ]
    key = "g1_per_k" if case in ("nonlinearity", "both") else "gain_drift_sigma"
    if case in ("bath_fluctuation", "common_mode"):  # the common part's sigma or NET
        key = "thermal_drift" if case == "bath_fluctuation" else "common_mode"
        rows = [{**r, "setup": {key: r["setup"][key][0]}} for r in rows]
    decades = sorted({math.floor(math.log10(abs(r["setup"][key]))) for r in rows})
    if len(decades) < 2:
        return []
    out = []
    for decade in decades:
        inside = [r for r in rows if math.floor(math.log10(abs(r["setup"][key]))) == decade]
        named = [r for r in inside if r["named"]]
        good = sum(r["within_3_sigma"] for r in named)
        out.append(
            f"    {key} in [1e{decade}, 1e{decade + 1}): named {len(named)}/{len(inside)}, "
            f"within 3 sigma {good}/{len(named)}"
        )
    return out


def expected_strengths(record: dict) -> dict:
    """{pair: |x| / sigma} of a crosstalk record's coupled pairs: x = sum c_ij NET_j / NET_i,
    sigma = 1 / sqrt(2 M) with M the rfft modes between 1 Hz (or three knees) and Nyquist
    (the fit's flat term alone; its sideband shapes and the lines left out add a little)."""
    setup = record["setup"]
    x = coupled_pairs(setup, record["truth"]["detectors"])
    low = max(1.0, 3 * setup["fknee_mhz"] * 1e-3)
    modes = (setup["sample_rate_hz"] / 2 - low) * setup["hours"] * 3600
    modes *= 1 - setup.get("flagged_fraction", 0.0)
    return {pair: abs(value) * math.sqrt(2 * modes) for pair, value in x.items()}


def _range(values: list[float]) -> str:
    return f"{min(values):.1f}-{max(values):.1f} ({len(values)})" if values else "none"


# the drawn amplitudes' ranges: flag -> (default bounds, what they bound)
RANGE_OPTIONS = {
    "--g1-range": ((2e-3, 3e-2), "|g1| [1/K]"),
    "--drift-range": ((3e-3, 3e-2), "GainDrifter's linear sigma"),
    "--slow-range": ((1e-2, 5e-2), "slow_drift's sigma"),
    "--crosstalk-range": ((1e-2, 5e-2), "|c_ij|"),
    "--thermal-range": ((1e-5, 1e-4), "common stream's K"),
    "--common-range": ((0.1, 0.5), "NET_c / NET"),
    "--hit-range": ((3.0, 300.0), "C2 / white noise"),
    "--step-range": ((0.1, 3.0), "|o| / white noise (|s| A_2: a tenth of it)"),
    "--bias-line-range": ((0.5, 3.0), "a bias line's |o| and |s| A_2 / white noise"),
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--per-case", type=int, default=20, help="recordings per case")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument(
        "--only",
        nargs="+",
        choices=CASES + WAFER_CASES + OTHER_CASES,
        default=list(CASES),
        help="cases",
    )
    parser.add_argument("--out", type=Path)
    parser.add_argument("--combine", nargs="+", type=Path, metavar="JSON")
    for flag, (default, meaning) in RANGE_OPTIONS.items():
        parser.add_argument(flag, nargs=2, type=float, default=default, help=meaning)
    parser.add_argument(
        "--net-spread", type=float, default=0.0, help="relative spread of the detectors' NETs"
    )
    arguments = parser.parse_args()
    if arguments.combine:
        records = [r for path in arguments.combine for r in json.loads(path.read_text())]
        records = [  # the common noise scored with the current truth
            {**r, **common_mode_pulls(r)} if "b_fitted" in r else r for r in records
        ]
        print("\n".join(summary(records)))
        return
    records = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        for case in arguments.only:
            for seed in range(arguments.first_seed, arguments.first_seed + arguments.per_case):
                ranges = (
                    arguments.g1_range,
                    arguments.drift_range,
                    arguments.slow_range,
                    arguments.crosstalk_range,
                    arguments.thermal_range,
                    arguments.common_range,
                    arguments.net_spread,
                    arguments.hit_range,
                    arguments.step_range,
                    arguments.bias_line_range,
                )
                record = when_memory_allows(case, seed, folder / f"{case}_{seed}", ranges)
                records.append(record)
                print(json.dumps(record), file=sys.stderr, flush=True)
                if arguments.out:
                    arguments.out.write_text(json.dumps(records, indent=1) + "\n")
    print("\n".join(summary(records)))


if __name__ == "__main__":
    main()
