"""One glitch's fit (:func:`hwp_tes_systematics.diagnose.effects.glitches.fit_glitch`): an
exponential tail is fitted as one, and a hit shaped by a readout filter (three samples
that fall faster than any exponential through its first one, as TOAST's InjectCosmicRays
writes them) keeps its first samples' departures from the tail, which then leave no
residual and count in the BIC."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hwp_tes_systematics.diagnose.effects.glitches import (
    DEPARTURE_MIN_SAMPLES,
    DEPARTURE_S,
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
    n_shaped = max(DEPARTURE_MIN_SAMPLES, math.ceil(DEPARTURE_S * FS_HZ))
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
