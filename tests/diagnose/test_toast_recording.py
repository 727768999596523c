"""TOAST 3 observation files as recordings (:mod:`hwp_tes_systematics.diagnose.toast_recording`).

The files are written by TOAST's own operators (:mod:`.toast_testbed`): the reader's
pointing, polarisation angles and HWP angle must reproduce TOAST's scan of a map to
rounding, its frame must be found in each of TOAST's three, its dipole must be TOAST's
to the solar-velocity difference, and the diagnosis must name what TOAST injected.
"""

from __future__ import annotations

import json
import re

import h5py
import healpy as hp
import numpy as np
import pytest

from hwp_tes_systematics.cli import main
from hwp_tes_systematics.diagnose.model import dipole_tod, scan_sky
from hwp_tes_systematics.diagnose.recording import read_recording
from hwp_tes_systematics.diagnose.recording_checks import RecordingError, recording_size
from hwp_tes_systematics.diagnose.testbed import sky_map
from hwp_tes_systematics.diagnose.toast_testbed import write_toast_recording

pytest.importorskip("toast", reason="the toast extra is not installed")

A2_K = 0.22  # a HWPSS amplitude [K_CMB] added to the TOAST signal (assumption, MFT-like)


@pytest.fixture(scope="module")
def sky_fits(tmp_path_factory):
    path = tmp_path_factory.mktemp("sky") / "sky.fits"
    hp.write_map(path, sky_map(), dtype=np.float64)
    return path


def test_the_reader_reproduces_toasts_scan_of_a_map_to_rounding(tmp_path, sky_fits):
    """TOAST's StokesWeights with a HWP and ScanHealpixMap, 14 detectors of 7 pixels
    (off-axis, orientations 0, 45, 90, 135 deg): d = I + eta [Q cos 2b + U sin 2b] equals
    the nominal model's sky at the read pointing, theta_k = 2 gamma - pi/2, chi = omega,
    to the rounding of TOAST's map (single precision)."""
    path = write_toast_recording(
        tmp_path, sky_fits, hours=0.2, seed=1, n_pixels=7, dipole=False, noise=False
    )
    recording = read_recording(path)
    assert recording.n_detectors == 14 and "frame G" in recording.source
    intensity, polarization, *_ = scan_sky(recording, sky_map())
    signal_rms = np.std(recording.tod)
    assert np.std(polarization) > 1e-3 * signal_rms  # the polarised sky is tested too
    # to TOAST's single-precision map (relative 6e-8): 1e-4 of the polarised signal, which
    # a polarisation angle off by 0.01 deg would exceed
    atol = 2e-7 * np.abs(sky_map()).max()
    assert atol < 2e-4 * np.std(polarization)
    np.testing.assert_allclose(recording.tod, intensity + polarization, rtol=0, atol=atol)


@pytest.mark.parametrize("coord", ["C", "E", "G"])
def test_each_frame_is_found_and_the_pointing_is_toasts(tmp_path, sky_fits, coord):
    """The frame comes from the spacecraft's position and velocity; the ecliptic pointing
    read, turned back to the file's frame, falls in TOAST's own pixels (PixelsHealpix)."""
    from toast import ops
    from toast.observation import default_values as defaults

    pixels = {}

    def keep_pixels(data):
        pointing = ops.PointingDetectorSimple(boresight=defaults.boresight_radec)
        op = ops.PixelsHealpix(nside=256, nest=False, detector_pointing=pointing)
        op.apply(data)
        observation = data.obs[0]
        pixels["toast"] = np.array(observation.detdata[op.pixels].data)
        ops.Delete(detdata=[op.pixels, pointing.quats]).apply(data)

    path = write_toast_recording(
        tmp_path, sky_fits, 0.1, 2, coord=coord, n_pixels=7, noise=False, edit=keep_pixels
    )
    recording = read_recording(path)
    assert f"frame {coord}" in recording.source
    from hwp_tes_systematics.diagnose.toast_recording import _frame_rotations

    to_file = _frame_rotations()[coord].inv()
    theta, phi = recording.pointings_ecl[..., 0], recording.pointings_ecl[..., 1]
    vectors = to_file.apply(hp.ang2vec(theta.ravel(), phi.ravel())).reshape(theta.shape + (3,))
    ours = hp.vec2pix(256, vectors[..., 0], vectors[..., 1], vectors[..., 2])
    assert np.mean(ours == pixels["toast"]) > 0.9999


def test_the_dipole_is_toasts_to_the_solar_velocity_difference(tmp_path, sky_fits):
    """TOAST's SimDipole (total) against litebird_sim's dipole with the file's velocity:
    the solar velocities differ by 0.26 km/s (370.08 against 369.82), ~2.5 uK at most."""
    path = write_toast_recording(tmp_path, sky_fits, 0.5, 3, noise=False)
    recording = read_recording(path)
    intensity, polarization, *_ = scan_sky(recording, sky_map())
    toast_dipole = recording.tod - intensity - polarization
    assert np.std(toast_dipole) > 5e-4
    assert np.max(np.abs(toast_dipole - dipole_tod(recording))) < 3e-6


def test_flags_units_segments_and_left_out_detectors(tmp_path, sky_fits):
    """Detector and shared flags (non-science bits), mK units, a detector flagged invalid
    in the observation (left out) and a segment read alone."""

    def edit(data):
        observation = data.obs[0]
        names = observation.local_detectors
        observation.detdata["flags"][names[0]][100:200] = 1  # invalid
        observation.detdata["flags"][names[1]][300:310] = 8  # not a non-science bit
        shared = np.array(observation.shared["flags"].data)
        shared[500:520] = 2
        observation.shared["flags"].set(shared, offset=(0,), fromrank=0)
        observation.update_local_detector_flags({names[3]: 1})

    path = write_toast_recording(tmp_path, sky_fits, 0.1, 4, n_pixels=7, noise=False, edit=edit)
    whole = read_recording(path)
    assert whole.n_detectors == 13 and recording_size(path)[0] == 13
    assert whole.flags[0, 100:200].all() and not whole.flags[1, 300:310].any()
    assert whole.flags[:, 500:520].all() and whole.flags.sum() == 100 + 13 * 20
    segment = read_recording(path, samples=(400, 1400))
    np.testing.assert_array_equal(segment.tod, whole.tod[:, 400:1400])
    np.testing.assert_allclose(segment.pointings_ecl, whole.pointings_ecl[:, 400:1400])
    with h5py.File(path, "a") as handle:
        signal = handle["detdata/signal"]
        signal[...] = signal[...] * 1e3
        signal.attrs["units"] = "mK"
    np.testing.assert_allclose(read_recording(path).tod, whole.tod, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize(
    "edit_file, message",
    [
        (lambda h: h["detdata/signal"].attrs.__setitem__("units", "W"), "expected a temperature"),
        (lambda h: h.__delitem__("shared/hwp_angle"), "rotating HWP"),
        (lambda h: h["shared/velocity"].__setitem__(..., 1.0), "cannot be told"),
        (lambda h: h.__delitem__("shared/times"), "shared/times"),
        (
            lambda h: h["instrument"].attrs.__setitem__(
                "site_class", "toast.instrument.GroundSite"
            ),
            "a ground observation",
        ),
        (lambda h: h["shared/times"].__setitem__(..., h["shared/times"][...] * 1.001), "disagrees"),
    ],
)
def test_bad_toast_files_are_refused_naming_the_problem(tmp_path, sky_fits, edit_file, message):
    path = write_toast_recording(tmp_path, sky_fits, 0.05, 5, noise=False)
    with h5py.File(path, "a") as handle:
        edit_file(handle)
    with pytest.raises(RecordingError, match=message) as error:
        read_recording(path)
    assert str(path) in str(error.value)


@pytest.mark.slow
@pytest.mark.parametrize(
    "case, options, a2_k",
    [
        ("clean", {}, 0.0),
        ("nonlinearity", {"a2_k": A2_K, "g1_per_k": 0.02}, A2_K),
        ("nonlinearity in segments", {"a2_k": A2_K, "g1_per_k": 0.02}, A2_K),
        ("gain drift", {"a2_k": A2_K, "gain_drift_sigma": 0.01}, A2_K),
    ],
)
def test_diagnose_names_what_toast_injected(tmp_path, sky_fits, capsys, case, options, a2_k):
    """Two hours of a TOAST pair with TOAST's dipole and noise through the command line:
    a clean recording raises no alarm; a nonlinearity is named with g1 within 3 sigma,
    also diagnosed in one-hour segments (each read from the file alone); TOAST's
    GainDrifter is named a gain drift."""
    path = write_toast_recording(tmp_path / "rec", sky_fits, 2.0, 11, **options)
    out = tmp_path / "out"
    segments = ["--segment-hours", "1"] if "segments" in case else []
    code = main(
        ["diagnose", str(path), "--sky", str(sky_fits), "--a2", str(a2_k), "--out", str(out), "-q"]
        + segments
    )
    assert code == 0
    result = json.loads((out / "diagnosis.json").read_text())
    names = [effect["name"] for effect in result["effects"]]
    if case == "clean":
        assert names == [] and not result.get("unexplained")
    elif case.startswith("nonlinearity"):
        assert names == ["tes_nonlinearity"]
        for parameter in result["effects"][0]["parameters"].values():
            assert abs(parameter["value"] - 0.02) < 3 * parameter["sigma"], parameter
    else:
        assert names[0] == "gain_drift"


@pytest.mark.slow
def test_a_readout_gain_drift_beside_the_nonlinearity_is_fitted_after_it(tmp_path, sky_fits):
    """TOAST's GainDrifter acts after the nonlinearity, as a readout gain: (1 + delta)(d +
    g1 d^2). Composed before it (D + g1 D^2, D = (1 + delta) d) the fit leaves g1 delta
    d^2, a 4f line following the drift (with ramps of a few per cent: other effects named,
    g1 many sigma off). The composed fit tries both orders and keeps the better: the two
    effects alone, g1 within 3 sigma of g1 / (1 + s / 2) (the ramp's mean in the gain)."""
    from hwp_tes_systematics.diagnose import diagnose

    truth: dict = {}
    path = write_toast_recording(
        tmp_path, sky_fits, 2.0, 3, a2_k=A2_K, g1_per_k=0.02, gain_drift_sigma=0.03, truth=truth
    )
    slopes = truth["gain_drift_slope"]
    assert max(abs(s) for s in slopes.values()) > 0.02  # a ramp the order shows on
    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    assert sorted(e["name"] for e in result["effects"]) == ["gain_drift", "tes_nonlinearity"]
    nonlinearity = next(e for e in result["effects"] if e["name"] == "tes_nonlinearity")
    order = re.search(
        r"the gain drift acts after it, as a readout gain.*chi\^2 lower by (\S+)",
        nonlinearity["evidence"],
    )
    assert order and float(order.group(1)) > 25  # the other order is ruled out
    for parameter in nonlinearity["parameters"].values():
        expected = 0.02 / (1 + slopes[parameter["detector"]] / 2)
        assert abs(parameter["value"] - expected) < 3 * parameter["sigma"], parameter


SIGMA_19HZ_K = 50e-6 * np.sqrt(19.0)  # the white noise per sample: NET sqrt(f_s)


def _direct_hits(draw_seed: int) -> dict:
    """The testbed's ``cosmic_rays``: 400 hits for TOAST to draw from, C2 30-300 times
    the white noise per sample, C1 5 % of it, tau 2-20 ms, 4e-3 hits per second, and a
    wafer noise of 0.3 times the white noise."""
    rng = np.random.default_rng(draw_seed)
    c2_k = 30 * SIGMA_19HZ_K * np.exp(rng.uniform(0.0, np.log(10.0), 400))
    return {
        "event_rate_hz": 4e-3,
        "hits": {"c1": 0.05 * c2_k, "c2": c2_k, "tau_ms": rng.uniform(2.0, 20.0, 400)},
        "wafer_noise_k": [0.0, 0.3 * SIGMA_19HZ_K],
        "pair_correlation": None,
    }


@pytest.mark.slow
def test_toasts_cosmic_rays_are_named_glitches(tmp_path, sky_fits):
    """TOAST's InjectCosmicRays on an hour of a pair at 19 Hz: direct hits (C1 + C2
    exp(-t / tau) at 1 kHz, tau 2-20 ms, resampled by TOAST to three samples) and its
    white wafer noise. The diagnosis names glitches and nothing else, leaves nothing
    unexplained, finds every hit above 20 sigma per sample at its first sample, and keeps
    the strong hits' departures from an exponential tail (TOAST's three samples fall
    faster than any exponential through the first)."""
    from hwp_tes_systematics.diagnose import diagnose

    sigma_k = SIGMA_19HZ_K
    rays = _direct_hits(5)
    truth: dict = {}
    path = write_toast_recording(
        tmp_path / "rec", sky_fits, 1.0, 7, a2_k=A2_K, cosmic_rays=rays, truth=truth
    )
    hits = truth["cosmic_ray_hits"]
    assert sum(len(h) for h in hits.values()) >= 10
    assert all(samples == 3 for h in hits.values() for _, samples, _ in h)

    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    assert [e["name"] for e in result["effects"]] == ["glitches"]
    assert not result["unexplained"]
    parameters = result["effects"][0]["parameters"].values()
    found = {}
    for p in parameters:
        if p["parameter"] == "time":
            found.setdefault(p["detector"], []).append(p["value"])
    sigma_all = sigma_k * np.hypot(1.0, 0.3)
    for name, detector_hits in hits.items():
        for first, _, peak in detector_hits:
            if abs(peak) > 20 * sigma_all:
                assert np.min(np.abs(np.array(found[name]) - first / 19.0)) < 1e-6, first
    assert any(p["parameter"] == "departure" for p in parameters)
    assert "depart from an exponential tail" in result["effects"][0]["evidence"]
    assert result["effects"][0]["scope"]["by"] == "detector"  # independent per detector


@pytest.mark.slow
def test_toasts_hits_shared_by_a_pair_are_coincident_glitches(tmp_path, sky_fits):
    """TOAST's direct hits of a pixel's first detector given to both its detectors (the
    second at 0.6 of the first's amplitude): glitches, scoped by coincidence, every
    shared hit above 20 sigma per sample in both a coincident event at its first sample,
    and the evidence calling them shared."""
    from hwp_tes_systematics.diagnose import diagnose

    sigma_k = SIGMA_19HZ_K
    rays = _direct_hits(9) | {"shared": {"by": "all", "scale": [1.0, 0.6]}}
    truth: dict = {}
    path = write_toast_recording(
        tmp_path / "rec", sky_fits, 1.0, 11, a2_k=A2_K, cosmic_rays=rays, truth=truth
    )
    first, second = truth["cosmic_ray_hits"].values()
    assert [h[0] for h in first] == [h[0] for h in second] and len(first) >= 4

    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    assert [e["name"] for e in result["effects"]] == ["glitches"]
    scope = result["effects"][0]["scope"]
    assert scope["by"] == "coincidence" and scope["p_value"] < 1e-9
    times = {float(label.split()[2]): names for label, names in scope["groups"].items()}
    sigma_all = sigma_k * np.hypot(1.0, 0.3)
    for start, _, peak in first:
        if 0.6 * abs(peak) > 20 * sigma_all:
            nearest = min(times, key=lambda t: abs(t - start / 19.0))
            assert abs(nearest - start / 19.0) < 0.01 and len(times[nearest]) == 2, start
    assert "shared by detectors" in result["effects"][0]["evidence"]


@pytest.mark.slow
def test_steps_on_toasts_tod_are_named_readout_steps(tmp_path, sky_fits):
    """TOAST's pair for an hour with a step in each detector (the testbed's, on TOAST's
    signal and noise): an offset of 0.7 times the white noise per sample at 1,000 s in the
    first, a gain of 0.2 times it over A_2 at 2,500 s in the second. readout_steps alone,
    each step in its detector with that part, time and value within 3 sigma."""
    from hwp_tes_systematics.diagnose import diagnose

    sigma_k = SIGMA_19HZ_K
    steps = [[0, 19_000, 0.7 * sigma_k, 0.0], [1, 47_500, 0.0, 0.2 * sigma_k / A2_K]]
    truth: dict = {}
    path = write_toast_recording(
        tmp_path / "rec", sky_fits, 1.0, 12, a2_k=A2_K, readout_steps=steps, truth=truth
    )
    assert sorted(len(v) for v in truth["readout_steps"].values()) == [1, 1]
    result = diagnose(read_recording(path), sky_map(), A2_K, figures=False).to_dict()
    assert [e["name"] for e in result["effects"]] == ["readout_steps"], result["effects"]
    parameters = result["effects"][0]["parameters"].values()
    names = list(truth["readout_steps"])
    for (detector, first, offset, gain), name in zip(steps, names, strict=True):
        mine = {p["parameter"]: p for p in parameters if p["detector"] == name}
        part, value = ("offset", offset) if offset else ("gain", gain)
        assert set(mine) == {part, "time"}, mine
        assert abs(mine[part]["value"] - value) < 3 * mine[part]["sigma"], mine
        assert abs(mine["time"]["value"] - first / 19.0) < 3 * mine["time"]["sigma"], mine


def test_toasts_pair_common_mode_is_not_common(tmp_path, sky_fits):
    """TOAST 3.0.6's InjectCosmicRays with its pair common mode at a correlation of 0.9:
    each detector's "common" part is drawn at its own counter, so the two detectors of a
    pixel stay uncorrelated (|rho| < 0.03 over 0.3 h at 19 Hz, 20,520 samples: 4 sigma),
    while the wafer noise's variance is (1 + 0.9) times its rms squared. If TOAST makes it
    common, this fails, and the cosmic-ray case of the rates benchmark should expect a
    common noise."""
    rays = {
        "event_rate_hz": 0.0,
        "hits": {"c1": [0.0], "c2": [1.0], "tau_ms": [1.0]},
        "wafer_noise_k": [0.0, 1e-3],
        "pair_correlation": 0.9,
    }
    options = {"n_pixels": 7, "noise": False, "dipole": False}
    with_rays = write_toast_recording(tmp_path / "a", sky_fits, 0.3, 5, cosmic_rays=rays, **options)
    without = write_toast_recording(tmp_path / "b", sky_fits, 0.3, 5, **options)
    wafer_noise = read_recording(with_rays).tod - read_recording(without).tod
    np.testing.assert_allclose(wafer_noise.std(axis=1), 1e-3 * np.sqrt(1.9), rtol=0.03)
    correlation = np.corrcoef(wafer_noise)
    pairs = [correlation[k, k + 1] for k in range(0, 14, 2)]
    assert max(abs(c) for c in pairs) < 0.03, pairs
