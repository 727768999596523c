"""Clean recordings: no mismatch reported; the false-alarm rate over 20 noise seeds.

A clean recording is the simulation itself plus litebird_sim noise (a seed the diagnosis
never sees). With the BIC threshold Delta BIC < -10 a false alarm needs a noise
fluctuation of Delta chi^2 > k ln N_eff + 10 (> 36 for the smallest effect), so the
target rate is far below 5 %; the test allows at most 1 in 20 recordings of 30 minutes.
"""

from __future__ import annotations

import pytest

from hwp_tes_systematics.diagnose.testbed import recorded, run

pytestmark = pytest.mark.slow

N_SEEDS = 20


def test_clean_recording_reports_no_mismatch(tmp_path):
    recording, _ = recorded(tmp_path, [], noise_seed=1, hours=1.0)
    result = run(recording, out_dir=tmp_path / "out")
    assert not result["mismatch_found"], result.effect_names
    assert result["effects"] == []
    assert result["chi2_after"] == result["chi2_before"]
    # the residual is consistent with the configured noise
    assert abs(result["chi2_before"] / result["n_eff"] - 1) < 5 * (2 / result["n_eff"]) ** 0.5
    for name in ("diagnosis.json", "diagnosis.md", "residual_spectrum.png", "residual_map.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert "No mismatch found" in (tmp_path / "out" / "diagnosis.md").read_text()


def test_false_alarm_rate_over_clean_seeds(tmp_path):
    alarms = []
    for seed in range(1000, 1000 + N_SEEDS):
        recording, _ = recorded(tmp_path, [], noise_seed=seed, hours=0.5, name=f"clean{seed}.h5")
        result = run(recording)
        if result["mismatch_found"]:
            alarms.append((seed, result.effect_names))
    print(f"false alarms: {len(alarms)} / {N_SEEDS}: {alarms}")
    assert len(alarms) <= 1, alarms
