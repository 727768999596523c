"""One glitch's fit (:func:`hwp_tes_systematics.diagnose.effects.glitches.fit_glitch`): an
exponential tail is fitted as one, and a hit shaped by a readout filter (three samples
that fall faster than any exponential through its first one, as TOAST's InjectCosmicRays
writes them) keeps its first samples' departures from the tail, which then leave no
residual and count in the BIC."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hwp_tes_systematics.diagnose.effects.event_groups import coincidences
from hwp_tes_systematics.diagnose.effects.glitches import (
    GlitchEvent,
    departure_samples,
    find_transients,
    fit_glitch,
    glitch_tod,
)

FS_HZ = 19.0
SIGMA_K = 1e-4  # white noise per sample
LN_N = math.log(1e5)  # the BIC's ln N per parameter, as for a pair-hour
EVENT = 3000  # the hit's first sample


def _noise(seed: int) -> tuple[np.ndarray, np.ndarray]:
    times_s = np.arange(6000) / FS_HZ
    return times_s, SIGMA_K * np.random.default_rng(seed).normal(size=times_s.size)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_exponential_tail_is_fitted_without_departures(seed):
    """A exp(-(t - t0)/tau), 50 sigma, tau 0.1 s: no departure kept, A within 3 sigma."""
    times_s, tod = _noise(seed)
    after = times_s[EVENT:] - times_s[EVENT]
    tod[EVENT:] += 50 * SIGMA_K * np.exp(-after / 0.1)
    event = fit_glitch(tod, times_s, EVENT, SIGMA_K, 0, 1.5 / FS_HZ, departure_chi2_per_sample=LN_N)
    assert event.departure_k == () and event.n_parameters == 3
    assert abs(event.amplitude_k - 50 * SIGMA_K) < 3 * event.sigma_amplitude_k


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_shaped_hit_keeps_its_departures(seed):
    """Three samples 1, 0.37, 0.10 of 200 sigma (TOAST's resampled 3 ms hit at 19 Hz): the
    exponential alone leaves a residual far above the noise on those samples; with the
    departures kept the event's samples are reproduced to the noise, and each departure
    counts as a parameter. Without the BIC's ln N (the transients of the unexplained
    search) no departure is fitted."""
    times_s, tod = _noise(seed)
    pulse = 200 * SIGMA_K * np.array([1.0, 0.37, 0.10])
    tod[EVENT : EVENT + 3] += pulse
    n_shaped = departure_samples(1 / FS_HZ)
    plain = fit_glitch(tod, times_s, EVENT, SIGMA_K, 0, 1.5 / FS_HZ)
    assert plain.departure_k == ()
    left = tod - glitch_tod(times_s, 1, [plain])[0]
    assert np.sum((left[EVENT : EVENT + n_shaped] / SIGMA_K) ** 2) > n_shaped * LN_N

    event = fit_glitch(tod, times_s, EVENT, SIGMA_K, 0, 1.5 / FS_HZ, departure_chi2_per_sample=LN_N)
    assert len(event.departure_k) == n_shaped and event.n_parameters == 3 + n_shaped
    assert event.sigma_departure_k == SIGMA_K
    left = tod - glitch_tod(times_s, 1, [event])[0]
    # the departures take the event's samples to the local offset c (a few sigma / sqrt(n))
    assert np.all(np.abs(left[EVENT : EVENT + n_shaped]) < 1e-9 + 2 * SIGMA_K)
    np.testing.assert_allclose(
        glitch_tod(times_s, 1, [event])[0][EVENT : EVENT + 3], pulse, atol=3 * SIGMA_K
    )


def test_two_hits_eight_samples_apart_are_two_events():
    """Hits 0.42 s apart in one group of samples above the threshold (TOAST drew two so
    close in a recording): the second is found once the first is subtracted; a hit closer
    than the departures' length would be one event with departures."""
    times_s, tod = _noise(4)
    hits = [(EVENT, 80 * SIGMA_K), (EVENT + 8, 40 * SIGMA_K)]
    for first, amplitude in hits:
        tod[first:] += amplitude * np.exp(-(times_s[first:] - times_s[first]) / 0.05)
    n = tod.size
    s = np.full(n // 2 + 1, n * SIGMA_K**2)  # the white noise's expected |R_f|^2
    scale = n * FS_HZ / 2  # so that the white noise per sample is SIGMA_K
    events = find_transients(
        np.fft.rfft(tod), s, np.ones(n, bool), times_s, scale, 0, departure_chi2_per_sample=LN_N
    )
    assert sorted(round(e.time_s * FS_HZ) for e in events) == [EVENT, EVENT + 8]
    for event, (_, amplitude) in zip(sorted(events, key=lambda e: e.time_s), hits, strict=True):
        assert abs(event.amplitude_k - amplitude) < 3 * event.sigma_amplitude_k


@pytest.mark.parametrize(("fs_hz", "expected"), [(19.0, 5), (20.0, 5), (10.0, 3), (100.0, 25)])
def test_the_departure_length_is_one_number_per_rate(fs_hz, expected):
    """ceil(0.25 s x fs), at least 3 samples, from the interval of rounded sample times
    as from the rate: at 20 Hz 0.25 s is five samples, not six."""
    times_s = 1.7e9 + np.arange(4) / fs_hz  # Unix times lose the interval's last digits
    assert departure_samples(1 / fs_hz) == expected
    assert departure_samples(times_s[1] - times_s[0]) == expected


def _events_at(indices_by_detector, times_s):
    return [
        GlitchEvent(detector, float(times_s[i]), 10 * SIGMA_K, 0.01)
        for detector, indices in enumerate(indices_by_detector)
        for i in indices
    ]


def test_chance_coincidences_match_their_expectation():
    """Independent Poisson hits (4 detectors, 20 each in 6000 samples, 10 % of one
    detector's samples flagged): the coincident pairs averaged over 400 draws equal the
    expected n_i n_j (2w + 1) / T_ij summed over pairs within 10 %, and fewer than 1 % of
    the draws are called more than chance."""
    rng = np.random.default_rng(7)
    times_s = np.arange(6000) / FS_HZ
    valid = np.ones((4, times_s.size), bool)
    valid[2, 1000:1600] = False
    observed, expected, called = [], [], 0
    for _ in range(400):
        indices = [rng.choice(np.flatnonzero(v), 20, replace=False) for v in valid]
        found = coincidences(_events_at(indices, times_s), times_s, valid)
        observed.append(found.observed_pairs)
        expected.append(found.expected_pairs)
        called += found.significant
    assert np.mean(observed) == pytest.approx(np.mean(expected), rel=0.1)
    assert called <= 4


def test_hits_shared_by_detectors_are_coincident():
    """Five hits each in three of four detectors (one a sample late in one of them), and
    independent ones: the five are the coincident groups, far beyond chance."""
    rng = np.random.default_rng(3)
    times_s = np.arange(6000) / FS_HZ
    shared = np.array([500, 1700, 2900, 4100, 5300])
    indices = [
        np.r_[shared, rng.choice(6000, 3)],
        np.r_[shared + 1, rng.choice(6000, 3)],
        np.r_[shared, rng.choice(6000, 3)],
        rng.choice(6000, 5),
    ]
    events = _events_at(indices, times_s)
    found = coincidences(events, times_s, np.ones((4, 6000), bool))
    assert found.significant
    big = [g for g in found.groups if len({events[i].detector for i in g}) == 3]
    assert sorted(min(round(events[i].time_s * FS_HZ) for i in g) for g in big) == list(shared)
