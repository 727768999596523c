"""Readout steps (:mod:`hwp_tes_systematics.diagnose.effects.steps`): the scan equals the
exact fit of each part, an offset step and a gain step are found with the right part and
values within 3 sigma, their times' errors cover the truth, pure noise gives none, and in
a simulated pair the diagnosis names the step and nothing else."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hwp_tes_systematics.diagnose.effects.step_fit import Bank, fit_templates, position_fits
from hwp_tes_systematics.diagnose.effects.step_scan import (
    PARTS,
    RAMP_CENTRES,
    carrier,
    edge_shape,
    masked_offset_norms,
    offset_norms,
    ramp_offset_terms,
    scan_parts,
    sharpness,
    step_scan,
    trend,
)
from hwp_tes_systematics.diagnose.effects.step_search import StepSearch, choose_parts
from hwp_tes_systematics.diagnose.effects.steps import find_steps, step_tod
from hwp_tes_systematics.diagnose.fourier import irfft, rfft
from hwp_tes_systematics.diagnose.linalg import cross

FS_HZ = 19.0
N = 19_000  # 1,000 s
F_HWP_HZ = 46 / 60
A2_K = 0.2
WHITE_K = 2e-4  # white noise per sample
FKNEE_HZ = 0.05
# a 300 uK offset step's significance in _case's noise, beside the linear trend (14 for
# the periodic residual's fit alone, which counts the jump back at the end)
STEP_SIGMAS = 9.8


def _search(w, valid, signal, times_s) -> StepSearch:
    return StepSearch.of(w, valid, signal, times_s, F_HWP_HZ)


def _trend_bank(w, valid) -> Bank:
    """What the offset is fitted beside: the recording's linear trend, and where samples
    are flagged the gap offset (the valid samples' constant)."""
    rows = gram = None
    if not valid.all():
        rows = rfft(valid * 1.0)[None]
        gram = cross(rows, rows, w)
    return Bank.of(rows, gram, rfft(trend(valid.size) * valid), w, valid.size)


def _fit_edge(r_f, w, valid, signal, shape, parts) -> float:
    """delta chi^2 of the exact Whittle fit of ``parts`` with the edge ``shape`` (offset:
    shape; gain: shape d), beside the linear trend."""
    shapes = {"offset": shape, "gain": shape * signal}
    templates = rfft(np.stack([shapes[part] for part in parts]) * valid)
    return fit_templates(templates, r_f, w, _trend_bank(w, valid))[0]


def _case(seed: int):
    """A carrier (the 2f HWPSS), weights w = 1/S (white + 1/f, DC and Nyquist left out) and
    a noise rfft drawn from S."""
    times_s = np.arange(N) / FS_HZ
    signal = A2_K * np.cos(4 * np.pi * F_HWP_HZ * times_s)
    freqs = np.fft.rfftfreq(N, 1 / FS_HZ)
    psd = N * WHITE_K**2 * (1 + (FKNEE_HZ / np.maximum(freqs, 1e-12)) ** 1.5)
    w = np.zeros(freqs.size)
    w[1:-1] = 1 / psd[1:-1]
    rng = np.random.default_rng(seed)
    noise_f = np.sqrt(psd / 2) * (rng.normal(size=freqs.size) + 1j * rng.normal(size=freqs.size))
    return times_s, signal, w, noise_f


def test_the_scan_equals_each_parts_exact_fit():
    """<T, R>^2 / <T, T> from cumulative sums equals the Fourier-domain fit of each
    template (the offset's beside the linear trend, the gain's against the carrier, its
    mean taken off), to 1e-3."""
    _, signal, w, noise_f = _case(1)
    valid = np.ones(N, bool)
    c = carrier(signal, 0.5 * F_HWP_HZ, FS_HZ)
    freqs = np.fft.rfftfreq(N, 1 / FS_HZ)
    w_c = float(np.median(w[np.abs(freqs - 2 * F_HWP_HZ) < 0.1 * F_HWP_HZ]))
    scans = step_scan(noise_f, w, valid, c, w_c)
    c_f = rfft(c)
    for index in (500, 7000, 15000):
        step = np.zeros(N)
        step[index:] = 1.0
        offset_f, gain_f = rfft(step), rfft(step * c)
        exact = fit_templates(offset_f[None], noise_f, w, _trend_bank(w, valid))[0]
        assert scans["offset"][index] == pytest.approx(exact, rel=1e-3)
        # the gain template projected off the carrier (the nominal 2f amplitude)
        projection = cross(c_f[None], gain_f, w)[0] / cross(c_f[None], c_f, w)[0]
        projected = gain_f - projection * c_f
        b = cross(projected[None], noise_f, w)[0]
        exact = b**2 / cross(projected[None], projected, w)[0]
        assert scans["gain"][index] == pytest.approx(exact, rel=0.05, abs=0.05)


def test_the_masked_offset_norm_is_the_steps_whittle_norm():
    """<H v, H v> at every t_s by the correlation over 2n samples equals n T^T K T with K
    the circulant of k = irfft(w), at an even and an odd length, with gaps at the start,
    inside and at the end; with no sample flagged it is the unmasked norm."""
    rng = np.random.default_rng(3)
    for n in (400, 401):
        freqs = np.fft.rfftfreq(n, 1 / FS_HZ)
        w = 1 / (1 + (FKNEE_HZ / np.maximum(freqs, freqs[1])) ** 1.5) * rng.uniform(0.5, 1.5)
        kernel = irfft(w, n=n)
        circulant = kernel[(np.arange(n)[:, None] - np.arange(n)[None, :]) % n]
        valid = rng.uniform(size=n) > 0.1
        valid[:7] = valid[150:190] = valid[-5:] = False
        exact = [
            n * (edge_shape(n, t) * valid) @ circulant @ (edge_shape(n, t) * valid)
            for t in range(n)
        ]
        assert np.allclose(
            masked_offset_norms(w, valid), exact, rtol=1e-10, atol=1e-12 * max(exact)
        )
        everything = np.ones(n, bool)
        assert np.allclose(masked_offset_norms(w, everything), offset_norms(w, n), rtol=1e-9)


def test_with_flags_the_offset_scan_equals_its_exact_fit_beside_the_trend():
    """With 2 % of the samples flagged (one gap, scattered samples), the offset scan's
    delta chi^2 equals the exact fit of H v beside the masked linear trend and the gap
    offset, before, inside and just after the gap and far from it, to 1e-6."""
    _, _, w, noise_f = _case(2)
    rng = np.random.default_rng(8)
    valid = rng.uniform(size=N) > 0.01
    valid[13_000:13_190] = False
    noise_f[0] = 0.0
    r_f = rfft((np.fft.irfft(noise_f, n=N) + 3e-4 * edge_shape(N, 9_000)) * valid)
    scan = scan_parts(r_f, w, valid, np.zeros(N), 1.0)
    for index in (500, 9_000, 12_990, 13_100, 13_190, 13_200, 17_000):
        exact = fit_templates(
            rfft(edge_shape(N, index) * valid)[None], r_f, w, _trend_bank(w, valid)
        )
        assert scan.chi2("offset")[index] == pytest.approx(exact.delta_chi2, rel=1e-6)


@pytest.mark.parametrize("part", ["offset", "gain"])
def test_the_sharpness_from_running_means_equals_the_exact_fits(part):
    """D (the step's delta chi^2 less the best ramp's over 3 min) and E (the step's
    information above 1 / 3 min) from the scan's running means equal those of exact
    Fourier fits of the step and of each ramp (no mask), to 10 % of E."""
    _, signal, w, noise_f = _case(4)
    valid = np.ones(N, bool)
    first, half = 9_000, int(90 * FS_HZ)
    step = edge_shape(N, first)
    change = 3e-4 * step if part == "offset" else 1e-3 * step * signal
    r_f = noise_f + rfft(change)
    c = carrier(signal, 0.5 * F_HWP_HZ, FS_HZ)
    freqs = np.fft.rfftfreq(N, 1 / FS_HZ)
    w_c = float(np.median(w[np.abs(freqs - 2 * F_HWP_HZ) < 0.1 * F_HWP_HZ]))
    scan = scan_parts(r_f, w, valid, c, w_c)
    d, e = sharpness(scan, first, half, (part,), (0, N), ramp_offset_terms(w, N, N // 2, half))
    exact_step = _fit_edge(r_f, w, valid, signal, step, (part,))
    centres = np.linspace(first - 2 * half, first + 2 * half, RAMP_CENTRES).astype(int)
    exact_ramp = max(
        _fit_edge(r_f, w, valid, signal, edge_shape(N, c, 2 * half), (part,)) for c in centres
    )
    value = scan.value(part, first)
    difference = step - edge_shape(N, first, 2 * half)
    shape = difference if part == "offset" else difference * signal
    shape_f = value * rfft(shape)
    exact_e = cross(shape_f[None], shape_f, w)[0]
    assert e == pytest.approx(exact_e, rel=0.1)
    assert abs(d - (exact_step - exact_ramp)) < 0.1 * exact_e
    assert d > 2 * np.sqrt(e)  # and it is sharp


@pytest.mark.parametrize("flagged", [False, True])
def test_an_offset_steps_significance_is_one_sigma_per_sigma_on_noise_that_does_not_wrap(
    flagged,
):
    """1/f noise recorded for 1,000 s out of a 4,000 s stream does not come back to where it
    started, as the Whittle likelihood's periodic residual would: fitted alone, an offset
    step's z = <T, R> / sqrt(<T, T>) at a fixed time spreads over more than 1.4 sigma;
    beside the linear trend (the scan's), over 1 within 15 % (100 draws, 3 times), with
    every sample valid or with 2 % flagged (a gap between the first two times: the gap
    offset fitted too; beside the trend alone the first time's z spreads over 2)."""
    _, _, w, _ = _case(1)
    freqs = np.fft.rfftfreq(4 * N, 1 / FS_HZ)
    psd = 4 * N * WHITE_K**2 * (1 + (FKNEE_HZ / np.maximum(freqs, 1e-12)) ** 1.5)
    psd[0] = 0.0
    rng = np.random.default_rng(5)
    valid = np.ones(N, bool)
    if flagged:
        valid[9_000:9_380] = False
    c = np.zeros(N)  # no carrier: the offset alone
    trend_alone = Bank.of(None, None, rfft(trend(N) * valid), w, N)
    alone, beside, before_gap = [], [], []
    for _ in range(100):
        stream_f = np.sqrt(psd / 2) * (
            rng.normal(size=freqs.size) + 1j * rng.normal(size=freqs.size)
        )
        r_f = rfft(np.fft.irfft(stream_f, n=4 * N)[:N] * valid)
        scan = scan_parts(r_f, w, valid, c, 1.0)
        for index in (3000, 9500, 16000):
            step_f = rfft(edge_shape(N, index) * valid)
            alone.append(
                cross(step_f[None], r_f, w)[0] / math.sqrt(cross(step_f[None], step_f, w)[0])
            )
            beside.append(scan.offset[index] * math.sqrt(scan.norms.inverse_norms["offset"][index]))
        if flagged:
            fit = fit_templates(rfft(edge_shape(N, 3000) * valid)[None], r_f, w, trend_alone)
            before_gap.append(fit.values[0] / math.sqrt(fit.covariance[0, 0]))
    assert np.std(alone) > 1.4
    assert np.std(beside) == pytest.approx(1.0, abs=0.15)
    if flagged:
        assert np.std(before_gap) > 2.0


@pytest.mark.parametrize("seed", range(1, 9))
def test_pure_noise_has_no_step(seed):
    times_s, signal, w, noise_f = _case(seed)
    found = find_steps(noise_f, _search(w, np.ones(N, bool), signal, times_s), 0, math.log(2 * N))
    assert found == []


@pytest.mark.parametrize("seed", range(1, 7))
@pytest.mark.parametrize("part", ["offset", "gain"])
def test_a_step_is_found_with_its_part_values_and_time(seed, part):
    """A 10-sigma offset (300 uK) or 20-sigma gain (4e-4 of A_2) step at a random time: one step,
    that part alone, its value within 3 sigma, its time within 3 of its error, which is
    wider than half a sample and than the span within 1 of the peak would say."""
    times_s, signal, w, noise_f = _case(seed)
    rng = np.random.default_rng(100 + seed)
    first = int(rng.uniform(0.2, 0.8) * N)
    truth = {"offset": 3e-4, "gain": 0.0} if part == "offset" else {"offset": 0.0, "gain": 4e-4}
    step = np.zeros(N)
    step[first:] = 1.0
    recorded_f = noise_f + rfft(step * (truth["offset"] + truth["gain"] * signal))
    (event,) = find_steps(
        recorded_f, _search(w, np.ones(N, bool), signal, times_s), 0, math.log(2 * N)
    )
    assert event.parts == (part,)
    # an offset's sharpness is measured (white noise above the knee); a gain step's
    # information above 1 / (3 min) is E ~ 24 at 20 sigma, not always enough to say
    assert event.sharp or part == "gain"
    value, sigma = (
        (event.offset_k, event.sigma_offset_k)
        if part == "offset"
        else (event.gain, event.sigma_gain)
    )
    assert abs(value - truth[part]) < 3 * sigma
    assert abs(event.time_s - times_s[first]) < 3 * event.sigma_time_s
    assert event.n_parameters == 3  # the part and its time (counted twice)


def test_a_sharp_part_near_a_broad_parts_peak_sets_the_steps_time():
    """choose_parts: a broad gain scan (Delta chi^2 190, its peak 300 samples before the
    step) beside a sharp offset cusp (176 at the step) gives both parts at the offset's
    sample, not at the gain's peak nor at the peak of their sum; an offset of noise (16)
    within the gain's span leaves the gain alone at its own peak."""
    ln_n = math.log(2 * N)
    samples = np.arange(N)
    gain = 190.0 - 4e-5 * (samples - 9_700.0) ** 2  # within 16 of its peak over +-630 samples
    cusp = 176.0 - 0.5 * np.abs(samples - 10_000.0)
    parts_at = choose_parts({"offset": np.clip(cusp, 0, None), "gain": gain}, ln_n)
    assert parts_at[1:3] == (PARTS, 10_000)
    noise = np.zeros(N)
    noise[9_900] = 16.0
    assert choose_parts({"offset": noise, "gain": gain}, ln_n)[1:3] == (("gain",), 9_700)
    # a gain peak 9 samples after the offset's, rising over its cusp faster than the cusp
    # falls: the parts' sum peaks 2 samples off the edge; the step is at the offset's
    rising = 190.0 - 0.15 * (samples - 10_009.0) ** 2
    narrow = np.clip(176.0 - 2.0 * np.abs(samples - 10_000.0), 0, None)
    assert int(np.argmax(narrow + rising)) == 10_002
    assert choose_parts({"offset": narrow, "gain": rising}, ln_n)[1:3] == (PARTS, 10_000)


@pytest.mark.parametrize("seed", range(1, 7))
def test_a_step_of_both_parts_is_found_at_its_offsets_time(seed):
    """An offset step of 300 uK (10 sigma) with a gain step of 2.5e-4 at the same time
    (12 sigma, its time known to tens of seconds): one step, both parts, within 3 sigma,
    at the offset's time (the offset's scan is the sharper)."""
    times_s, signal, w, noise_f = _case(seed)
    rng = np.random.default_rng(200 + seed)
    first = int(rng.uniform(0.3, 0.7) * N)
    recorded_f = noise_f + rfft(edge_shape(N, first) * (3e-4 + 2.5e-4 * signal))
    (event,) = find_steps(
        recorded_f, _search(w, np.ones(N, bool), signal, times_s), 0, math.log(2 * N)
    )
    assert event.parts == PARTS
    assert abs(event.offset_k - 3e-4) < 3 * event.sigma_offset_k
    assert abs(event.gain - 2.5e-4) < 3 * event.sigma_gain
    assert abs(event.time_s - times_s[first]) < 3 * event.sigma_time_s


@pytest.mark.parametrize("seed", range(1, 4))
@pytest.mark.parametrize("part", ["offset", "gain"])
def test_a_smooth_change_is_not_a_step(seed, part):
    """A sinusoidal modulation of period 900 s (an offset of 300 uK, or 2 % of the 2f
    amplitude): no candidate is a sharp step; the 2f modulation's are all dropped (a
    change over three minutes fits far better), an offset's at most kept as not told
    apart from one."""
    times_s, signal, w, noise_f = _case(seed)
    wave = np.sin(2 * np.pi * times_s / 900.0)
    change = 3e-4 * wave if part == "offset" else 0.02 * wave * signal
    found = find_steps(
        noise_f + rfft(change), _search(w, np.ones(N, bool), signal, times_s), 0, math.log(2 * N)
    )
    assert not any(step.sharp for step in found), found
    if part == "gain":
        assert found == []


def test_steps_add_to_the_signal_they_scale():
    """step_tod: H(t - t_s) [o + s d] in the detector that stepped, zero elsewhere."""
    from hwp_tes_systematics.diagnose.effects.step_search import StepEvent

    times_s = np.arange(10) / FS_HZ
    signal = np.vstack([np.arange(10.0), np.ones(10)])
    tod = step_tod(times_s, signal, [StepEvent(0, times_s[4], 0.5, 0.1)])
    assert np.allclose(tod[0], np.where(np.arange(10) >= 4, 0.5 + 0.1 * np.arange(10), 0.0))
    assert np.all(tod[1] == 0)


@pytest.mark.slow
def test_a_pairs_steps_are_named_with_their_values(tmp_path):
    """A 1-h M1-140 pair: an offset step (150 uK, 8 sigma) in one detector and a gain step (2e-4)
    in the other, written to HDF5 and read back; the diagnosis, told nothing, names
    readout_steps alone, each detector's step with its part within 3 sigma and its time
    within 3 of its error (which 98 % of simulated steps are: noise seed 301 puts this
    offset step 4.7 errors late, one of the 2 %; the seed here is 302)."""
    from hwp_tes_systematics.diagnose.recording import read_recording, write_recording
    from hwp_tes_systematics.diagnose.simulate import simulate_recording
    from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, run, sky_map

    recording = simulate_recording(CHANNEL, 1.0, MASTER_SEED, 302, sky_map(), A2_K)
    first = int(np.searchsorted(recording.times_s, 1700.0))
    recording.tod[0, first:] += 1.5e-4
    recording.tod[1, 2 * first :] *= 1 + 2e-4
    write_recording(tmp_path / "steps.h5", recording)
    result = run(read_recording(tmp_path / "steps.h5"), figures=False)
    assert result.effect_names == ["readout_steps"], result.effect_names
    # sought only under the noise refitted on the first pass's residual: not among the
    # first step's candidates, added in the second pass
    assert "readout_steps" not in result["steps"][0]["candidates"]
    assert [s["added"] for s in result["steps"] if s["added"]] == ["readout_steps"]
    parameters = result["effects"][0]["parameters"]
    names = recording.detector_names
    offset = next(v for v in parameters.values() if v["parameter"] == "offset")
    gain = next(v for v in parameters.values() if v["parameter"] == "gain")
    assert offset["detector"] == names[0] and abs(offset["value"] - 1.5e-4) < 3 * offset["sigma"]
    assert gain["detector"] == names[1] and abs(gain["value"] - 2e-4) < 3 * gain["sigma"]
    times = {v["detector"]: v for v in parameters.values() if v["parameter"] == "time"}
    for name, truth_s in (
        (names[0], recording.times_s[first]),
        (names[1], recording.times_s[2 * first]),
    ):
        assert abs(times[name]["value"] - truth_s) < 3 * times[name]["sigma"]
    assert result["unexplained"] == []


@pytest.mark.slow
def test_a_gain_step_is_relative_to_the_signal_before_it(tmp_path):
    """A 2 % gain step 600 s into a 1-h pair: the adjusted A_2, fitted to the whole
    recording, holds 0.83 of it, so a gain read against it is off by s f_after = 1.7 %
    of s (25 of its errors); referred to the 2f amplitude before the step it is within 3
    sigma of 0.02."""
    from hwp_tes_systematics.diagnose.recording import read_recording, write_recording
    from hwp_tes_systematics.diagnose.simulate import simulate_recording
    from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, run, sky_map

    recording = simulate_recording(CHANNEL, 1.0, MASTER_SEED, 303, sky_map(), A2_K)
    first = int(np.searchsorted(recording.times_s, recording.times_s[0] + 600.0))
    recording.tod[0, first:] *= 1.02
    write_recording(tmp_path / "gain_step.h5", recording)
    result = run(read_recording(tmp_path / "gain_step.h5"), figures=False)
    assert result.effect_names == ["readout_steps"], result.effect_names
    parameters = result["effects"][0]["parameters"]
    (gain,) = [v for v in parameters.values() if v["parameter"] == "gain"]
    assert gain["detector"] == recording.detector_names[0]
    assert abs(gain["value"] - 0.02) < 3 * gain["sigma"], gain
    assert 0.02 * 0.0083 > 5 * gain["sigma"]  # the bias corrected is one it could see


def test_the_evidence_says_which_steps_are_not_told_apart_from_a_ramp():
    """A step marked not sharp is said to be one a smooth change over RAMP_S fits as well;
    a sharp one is not."""
    from types import SimpleNamespace

    from hwp_tes_systematics.diagnose.effects.steps import ReadoutSteps, StepEvent

    ev = SimpleNamespace(ctx=SimpleNamespace(detector_names=["A"]))
    sharp = StepEvent(0, 100.0, 1e-4, 0.0, 1e-5, 0.0, 10.0, 0.1, ("offset",), True)
    unresolved = StepEvent(0, 300.0, 1e-4, 0.0, 1e-5, 0.0, 8.0, 2.0, ("offset",), False)
    said = ReadoutSteps().evidence(ev, SimpleNamespace(events=[sharp]))
    assert "not told apart" not in said and "A at t = 100.0" in said
    said = ReadoutSteps().evidence(ev, SimpleNamespace(events=[sharp, unresolved]))
    assert said.count("not told apart") == 2 and "1 of them" in said


@pytest.mark.parametrize("seed", range(1, 4))
def test_a_gap_leaves_the_scan_of_noise_below_a_steps_price(seed):
    """Noise with 2 % of its samples flagged: the offset scan's largest delta chi^2 stays
    below the 3 ln N a step pays (the trend's masked part beside a norm that ignored the
    mask made it 38-89 here)."""
    _, _, w, noise_f = _case(seed)
    valid = np.ones(N, bool)
    valid[13_000:13_380] = False
    noise_f[0] = 0.0
    r_f = rfft(np.fft.irfft(noise_f, n=N) * valid)
    scan = scan_parts(r_f, w, valid, np.zeros(N), 1.0)
    edge = int(60 * FS_HZ)
    assert scan.chi2("offset")[edge:-edge].max() < 3 * math.log(2 * N)


@pytest.mark.parametrize("seed", range(1, 4))
def test_a_step_is_sharp_with_flags_far_from_it(seed):
    """Flagged samples (2 %, 400 s away) leave a 10-sigma offset step found and sharp."""
    times_s, signal, w, noise_f = _case(seed)
    valid = np.ones(N, bool)
    valid[13_000:13_380] = False
    first = 5_400
    noise_f[0] = 0.0  # the DC mode is not fitted (w = 0 there)
    tod = (np.fft.irfft(noise_f, n=N) + 3e-4 * edge_shape(N, first)) * valid
    found = find_steps(rfft(tod), _search(w, valid, signal, times_s), 0, math.log(2 * N))
    assert len(found) == 1 and found[0].sharp and found[0].parts == ("offset",)


def test_a_level_that_comes_back_is_not_two_steps():
    """A 10-sigma offset that returns 60 s later (a transient) gives no step; one that
    stays gives one."""
    times_s, signal, w, noise_f = _case(5)
    valid = np.ones(N, bool)
    box = edge_shape(N, 8_000) - edge_shape(N, 8_000 + int(60 * FS_HZ))
    for change, expected in ((box, 0), (edge_shape(N, 8_000), 1)):
        r_f = noise_f + rfft(3e-4 * change)
        found = find_steps(r_f, _search(w, valid, signal, times_s), 0, math.log(2 * N))
        assert len(found) == expected, found


def test_the_fits_at_many_positions_equal_each_positions_own_fit():
    """:func:`position_fits` (its inner products and Gram matrix moved sample by sample
    from one transform per part) equals :func:`fit_templates` on the
    transform at each position: delta chi^2, values, covariance and the change to the
    joint model, beside a bank of two templates, with flagged samples between positions,
    at an even and an odd number of samples."""
    for n in (N, N - 1):
        _check_position_fits(n)


def _check_position_fits(n):
    times_s, signal, w, noise_f = _case(7)
    times_s, signal = times_s[:n], signal[:n]
    w, noise_f = w[: n // 2 + 1].copy(), noise_f[: n // 2 + 1].copy()
    noise_f[0] = 0.0  # no 1/f power at f = 0
    w[0], w[-1] = w[1], w[-2]  # the zero and last frequencies weighted too
    valid = np.ones(n, bool)
    valid[5_000:5_010] = False
    valid[8_996:8_999] = False
    rows = rfft(np.stack([np.sin(0.01 * times_s), np.cos(0.003 * times_s) * signal]) * valid)
    bank = Bank.of(rows, cross(rows, rows, w), rfft(trend(n) * valid), w, n)
    r_f = rfft((irfft(noise_f, n=n) + 3e-4 * edge_shape(n, 9_000)) * valid)
    positions = [8_990, 8_995, 9_000, 9_004]
    parts = ("offset", "gain")
    fits = position_fits(r_f, w, valid, signal, positions, bank, parts)
    alone = position_fits(r_f, w, valid, signal, positions[2:3], bank, parts)[0]
    assert alone.delta_chi2 == pytest.approx(fits[2].delta_chi2, rel=1e-9)
    for i, fit in zip(positions, fits, strict=True):
        shapes = {"offset": valid * 1.0, "gain": signal * valid}
        templates = rfft(np.stack([edge_shape(n, i) * shapes[part] for part in parts]))
        own = fit_templates(templates, r_f, w, bank)
        assert fit.delta_chi2 == pytest.approx(own.delta_chi2, rel=1e-9)
        assert np.allclose(fit.values, own.values, rtol=1e-8, atol=0)
        assert np.allclose(fit.covariance, own.covariance, rtol=1e-8, atol=0)
        change, own_change = fit.change_f(), own.change_f()
        assert np.allclose(change, own_change, rtol=0, atol=1e-8 * np.abs(own_change).max())
    assert max(range(len(fits)), key=lambda j: fits[j].delta_chi2) == 2


def _bias_line(seed: int, weak_k: float):
    """Five detectors of one bias line's residuals (rfft): 10-sigma offset steps in 0-2 at
    one time, a step of ``weak_k`` in 3 at that time, none in 4; a fake problem with their
    weights for :meth:`ReadoutSteps.complete_events`."""
    from types import SimpleNamespace

    times_s, signal, w, _ = _case(seed)
    first = 9_000
    residuals = []
    for k, offset in enumerate((3e-4, 3e-4, 3e-4, weak_k, 0.0)):
        noise_f = _case(100 * seed + k)[3]
        residuals.append(noise_f + rfft(offset * edge_shape(N, first)))
    valid = np.ones((5, N), bool)
    ctx = SimpleNamespace(
        n_detectors=5,
        times_s=times_s,
        d_nom=np.tile(signal, (5, 1)),
        valid=valid,
        sampling_rate_hz=FS_HZ,
        f_hwp_hz=F_HWP_HZ,
        detector_names=list("ABCDE"),
    )
    problem = SimpleNamespace(
        ctx=ctx, valid=valid, w_nom=[w] * 5, derived={}, ln_n_eff=math.log(2 * N), workers=1
    )
    return problem, residuals, times_s[first]


@pytest.mark.parametrize("seed", range(1, 5))
def test_a_bias_lines_weak_detector_is_found_at_the_lines_time(seed):
    """Three detectors step together by 10 sigma (beyond chance), a fourth by half of it
    (delta chi^2 ~ 25 at the known time, where it pays ln N = 10.5; a search over every
    time asks 3 ln N and beats a noise peak of ~20): each search alone misses the fourth,
    the line's time finds it
    with its offset within 3 sigma and its time not counted; the fifth, which did not step,
    gets nothing."""
    from types import SimpleNamespace

    from hwp_tes_systematics.diagnose.effects.steps import ReadoutSteps

    effect = ReadoutSteps()
    weak_k = 3e-4 * math.sqrt(25 / STEP_SIGMAS**2)
    problem, residuals, time_s = _bias_line(seed, weak_k)
    found = [e for k in range(5) for e in effect.find(problem, k, residuals[k])]
    assert sorted({e.detector for e in found}) == [0, 1, 2]
    completed = effect.complete_events(problem, found, lambda k: (residuals[k], None, None))
    (added,) = completed[len(found) :]
    assert added.detector == 3 and added.shared_time and added.parts == ("offset",)
    assert added.n_parameters == 1 and abs(added.time_s - time_s) <= 3 * added.sigma_time_s
    assert abs(added.offset_k - weak_k) < 3 * added.sigma_offset_k
    scope = effect.scope(problem.ctx, SimpleNamespace(events=completed))
    assert scope["by"] == "coincidence"
    assert list(scope["groups"].values()) == [["A", "B", "C", "D"]]
    said = effect.evidence(SimpleNamespace(ctx=problem.ctx), SimpleNamespace(events=completed))
    assert "D at t" in said and "(at its line's time)" in said and "1 of them found at" in said


def test_a_bias_lines_steps_all_take_the_parts_any_of_them_shows():
    """Three detectors step together in offset (10 sigma) and gain (4e-4 of A_2), but the
    third's offset is 2 sigma and its own fit at the step (as its search would give it)
    has the gain alone: at the line's time every member takes both parts, the third's
    offset within 3 sigma of the truth."""
    from hwp_tes_systematics.diagnose.effects.step_search import fit_step
    from hwp_tes_systematics.diagnose.effects.steps import ReadoutSteps

    effect = ReadoutSteps()
    problem, residuals, time_s = _bias_line(3, 0.0)
    _, signal, _, _ = _case(3)
    first = round(time_s * FS_HZ)
    offsets = (3e-4, 3e-4, 3e-4 * 2 / STEP_SIGMAS)
    found = []
    for k, offset in enumerate(offsets):
        residuals[k] = _case(300 + k)[3] + rfft(edge_shape(N, first) * (offset + 4e-4 * signal))
        search = effect._search(problem, k)
        parts = ("gain",) if k == 2 else ("offset", "gain")
        event, _ = fit_step(
            residuals[k],
            search.w,
            search.valid,
            signal,
            search.times_s,
            first,
            k,
            search.bank(),
            parts,
            0,
        )
        found.append(event)
    completed = effect.complete_events(problem, found, lambda k: (residuals[k], None, None))
    line = {e.detector: e for e in completed if e.detector < 3}
    assert all(e.parts == ("offset", "gain") for e in line.values())
    assert all(abs(e.time_s - time_s) < 3 * e.sigma_time_s for e in line.values())
    assert abs(line[2].offset_k - offsets[2]) < 3 * line[2].sigma_offset_k
    assert abs(line[2].gain - 4e-4) < 3 * line[2].sigma_gain


def test_two_detectors_stepping_together_are_not_a_line():
    """Two detectors stepping at one time in 1,000 s coincide by chance with p ~ 6e-4,
    short of the 5 sigma a line asks: no other detector is fitted at their time, and a
    weak step there (4 sigma: a line's time would find it) stays unfound."""
    from hwp_tes_systematics.diagnose.effects.steps import ReadoutSteps

    effect = ReadoutSteps()
    problem, residuals, _ = _bias_line(8, 3e-4 * 4 / STEP_SIGMAS)
    residuals[2] = _case(802)[3]  # no step
    found = [e for k in range(5) for e in effect.find(problem, k, residuals[k])]
    assert sorted(e.detector for e in found) == [0, 1]
    completed = effect.complete_events(problem, found, lambda k: (residuals[k], None, None))
    assert completed == found


@pytest.mark.parametrize("seed", range(1, 4))
def test_a_bias_lines_steps_are_put_at_its_one_time(seed):
    """Five detectors step together by 1.2 sigma per sample (delta chi^2 ~ 1.4 per sample
    moved): each detector's own time scatters by a sample or more, the line's summed
    profile has five times the slope. Each is refitted at the line's time: every step
    within 3 of the line's error of the truth (that error at most the members'
    smallest), its offset within 3 sigma, the time counted once."""
    from hwp_tes_systematics.diagnose.effects.steps import ReadoutSteps

    effect = ReadoutSteps()
    problem, residuals, time_s = _bias_line(seed, 3e-4)
    offset_k = 1.2 * WHITE_K
    for k in range(5):
        residuals[k] = _case(100 * seed + k)[3] + rfft(offset_k * edge_shape(N, 9_000))
    found = [e for k in range(5) for e in effect.find(problem, k, residuals[k])]
    assert sorted(e.detector for e in found) == [0, 1, 2, 3, 4]
    completed = effect.complete_events(problem, found, lambda k: (residuals[k], None, None))
    assert len(completed) == 5 and len({e.time_s for e in completed}) == 1
    assert sum(not e.shared_time for e in completed) == 1
    sigma_s = completed[0].sigma_time_s
    assert all(e.sigma_time_s == sigma_s for e in completed)
    assert sigma_s <= min(e.sigma_time_s for e in found)
    assert abs(completed[0].time_s - time_s) <= 3 * sigma_s
    for e in completed:
        assert abs(e.offset_k - offset_k) < 3 * e.sigma_offset_k
