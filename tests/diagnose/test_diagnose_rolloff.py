"""The detector time constant from the noise's roll-off (issue 29, item 3): the lines cannot
show tau (its 2f lag is inside the 2f phase adjustment and the nonlinearity's 4f line lags
twice as much), the noise that passes the detector's pole can. Against a synthetic noise
stream of known tau; end to end with the nonlinearity, at MFT (M1-140) and HFT (H3-402)
rates; no roll-off found in white noise or when the pole acts on the signal alone."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.fft
from helpers import gain_sidebands

from hwp_tes_systematics.diagnose import (
    diagnose,
    read_recording,
    simulate_recording,
    write_recording,
)
from hwp_tes_systematics.diagnose.effects.fluctuations import WithExcess, sideband_psd
from hwp_tes_systematics.diagnose.effects.rolloff import fit_rolloff, rolloff
from hwp_tes_systematics.diagnose.noise import NoiseModel
from hwp_tes_systematics.diagnose.testbed import MASTER_SEED, nominal, sky_map

RATE_HZ = 31.0
N = 2**18  # 2.3 h


def noise_stream(tau_s: float, seed: int) -> np.ndarray:
    """White + 1/f noise (NET 50 uK sqrt(s), knee 20 mHz) through a single pole of tau."""
    rng = np.random.default_rng(seed)
    freqs = scipy.fft.rfftfreq(N, 1 / RATE_HZ)
    white = rng.standard_normal(N) * 50e-6 * math.sqrt(RATE_HZ)
    spectrum = scipy.fft.rfft(white) * np.sqrt(1 + 0.02 / np.maximum(freqs, freqs[1]))
    spectrum *= 1.0 / (1.0 + 2j * np.pi * freqs * tau_s)
    return scipy.fft.irfft(spectrum, n=N)


def held_excess(amplitude_k=0.3, gain_amplitude=6e-3, slope=1.0) -> WithExcess:
    """The noise of ``noise_stream`` with the sidebands of ``helpers.gain_sidebands`` as its
    excess."""
    freqs = scipy.fft.rfftfreq(N, 1 / RATE_HZ)
    excess = sideband_psd(freqs, 1.3, amplitude_k, gain_amplitude, slope, RATE_HZ / N)
    return WithExcess(NoiseModel(50e-6, 0.02, 1.0, 1e-5), freqs, excess)


def fitted(streams, start=None):
    ctx = SimpleNamespace(
        n_samples=N,
        sampling_rate_hz=RATE_HZ,
        f_hwp_hz=0.65,
        f_spin_hz=1 / 1200,
        valid=np.ones((len(streams), N), dtype=bool),
    )
    residual_f = scipy.fft.rfft(np.array(streams), axis=-1)
    used = np.ones(residual_f.shape[1], dtype=bool)
    used[0] = used[-1] = False
    start = start or [NoiseModel(50e-6, 0.02, 1.0, 1e-5)] * len(streams)
    return fit_rolloff(ctx, residual_f, start, used, math.log(2 * used.sum() * len(streams)))


def test_the_noise_gives_tau_within_its_error_and_nothing_in_white_noise():
    fit = fitted([noise_stream(4e-3, 1), noise_stream(0.0, 2)])
    assert abs(fit.tau_s[0] - 4e-3) < 3 * fit.sigma_tau_s[0]
    assert fit.sigma_tau_s[0] < 0.5e-3  # ~40 sigma at 2.3 h of 31 Hz
    assert fit.tau_s[1] < 3 * fit.sigma_tau_s[1]  # the white one: consistent with none
    assert fit.delta_bic < -100
    white = fitted([noise_stream(0.0, 3), noise_stream(0.0, 4)])
    assert white.delta_bic > 0  # no roll-off claimed
    assert rolloff(RATE_HZ / 2, (4e-3) ** 2) == pytest.approx(
        1 / (1 + (np.pi * RATE_HZ * 4e-3) ** 2)
    )


def test_a_gain_fluctuations_sidebands_are_not_a_roll_off():
    """Issue 29 item 2 (litebird_sim's thermal gain drift reported with a spurious time
    constant): the sidebands' wings fall away from 2 f_HWP like a roll-off. With them held
    in the noise (as the pipeline does once gain_fluctuations is taken) no tau is claimed
    and the white level and knee are the noise's; the same data fitted without them pass
    the wings for a roll-off or a 1/f, which this test shows the held excess prevents."""
    streams = [
        noise_stream(0.0, 5) + gain_sidebands(N, RATE_HZ, 7),
        noise_stream(0.0, 6) + gain_sidebands(N, RATE_HZ, 7),
    ]
    held = fitted(streams, [held_excess()] * 2)
    assert held.delta_bic > 0  # no roll-off claimed
    for model in held.noise:
        assert isinstance(model, WithExcess)  # the excess stays in the noise model
        assert model.net_k_sqrt_s == pytest.approx(50e-6, rel=0.02)
        assert 0.01 < model.fknee_hz < 0.04
    blind = fitted(streams)
    assert not all(0.01 < m.fknee_hz < 0.04 and m.tau_s == 0 for m in blind.noise)


@pytest.mark.slow
@pytest.mark.parametrize(("channel", "g1"), [("M1-140", -3e-3), ("H3-402", -5e-4)])
def test_a_time_constant_beside_the_nonlinearity_is_found_from_the_noise(tmp_path, channel, g1):
    """2 h pairs, tau = 5 ms acting on the signal and the detector noise, then the
    nonlinearity: both found, each detector's tau within 3 sigma; the same pole on the
    signal alone shows nothing in the noise and is left in the 2f phase adjustment."""
    a2 = nominal(channel)["a2_k"]
    found = {}
    for through_noise in (True, False):
        tau = {"tau": 5e-3, "through_noise": through_noise}
        effects = [("detector_time_constant", tau), ("tes_nonlinearity", {"g1": g1})]
        recording = simulate_recording(channel, 2.0, MASTER_SEED, 8200, sky_map(), a2, effects)
        path = write_recording(tmp_path / f"{through_noise}.h5", recording)
        found[through_noise] = diagnose(read_recording(path), sky_map(), a2, figures=False)
    with_noise, signal_only = found[True], found[False]
    assert set(with_noise.effect_names) == {"tes_nonlinearity", "detector_time_constant"}, (
        with_noise.effect_names,
        with_noise["unexplained"],
    )
    for k in range(2):
        tau = with_noise.parameter("detector_time_constant", "tau", k)
        assert abs(tau["value"] - 5e-3) < 3 * tau["sigma"], tau
        g1_fit = with_noise.parameter("tes_nonlinearity", "g1", k)
        assert abs(g1_fit["value"] - g1) < 4 * g1_fit["sigma"], g1_fit
    assert "rolls off" in with_noise.effect("detector_time_constant")["evidence"]
    assert signal_only.effect_names == ["tes_nonlinearity"]
    assert signal_only["noise"]["rolloff"]["delta_bic"] > 0


@pytest.mark.slow
def test_a_time_constant_beside_a_strong_4f_line_is_found_across_a_gap(tmp_path):
    """H3-402, g1 = -3e-3 (a 21 mK 4f line and as much DC), tau = 5 ms through the noise,
    3 h with 10 % of the samples NaN: the two effects alone, tau within 3 sigma, nothing
    unexplained. The nonlinearity's DC cut by the gap is no longer the DC mode the fit leaves
    out: unfitted in the nominal fit, it went into the gain, which left the dipole (1.5 mK
    at f_spin) in the residual; the noise then took a gain fluctuation and tau came out at
    10 ms (nominal.fit_nominal fits a constant beside the adjustments when samples are
    flagged)."""
    a2 = nominal("H3-402")["a2_k"]
    effects = [
        ("detector_time_constant", {"tau": 5e-3, "through_noise": True}),
        ("tes_nonlinearity", {"g1": -3e-3}),
    ]
    recording = simulate_recording("H3-402", 3.0, MASTER_SEED, 8201, sky_map(), a2, effects)
    n = recording.tod.shape[1]
    recording.tod[:, int(0.35 * n) : int(0.45 * n)] = np.nan
    path = write_recording(tmp_path / "gapped.h5", recording)
    result = diagnose(read_recording(path), sky_map(), a2, figures=False)
    assert set(result.effect_names) == {"tes_nonlinearity", "detector_time_constant"}, (
        result.effect_names,
        result["unexplained"],
    )
    assert not result["unexplained"]
    for k in range(2):
        tau = result.parameter("detector_time_constant", "tau", k)
        assert abs(tau["value"] - 5e-3) < 3 * tau["sigma"], tau
