"""Are the gain fluctuation's errors its scatter? litebird_sim's thermal gain drift on pairs.

    python benchmarks/diagnose_fluctuation_errors.py --seeds 16 --hours 2 --out errors.json
    python benchmarks/diagnose_fluctuation_errors.py --channel H3-402 --mismatch 0.1

Each recording: a pair of ``--channel`` simulated with random nominal errors about the
channel's nominal A_2 (diagnose.testbed, as the rates benchmarks) and its own noise seed,
then litebird_sim's ``apply_gaindrift_to_tod`` (THERMAL_GAIN, one focal-plane group,
``--sigma-drift``, ``--mismatch``, its own stream per recording). The diagnosis is told
nothing. Where it names ``gain_fluctuations``, its fitted (a, beta, rho) are compared with
the generator's: beta = alpha_drift (1), a = sqrt(2) sigma_drift (T_fluct / T_bath)
(f_knee / f_ref)^(beta / 2) (exact for ``--mismatch 0``, the default; with a mismatch m
each detector's factor is 1 + m u, u uniform in [0, 1], and a's truth is taken at u = 1/2),
rho = 1 for a stream common to the detectors (mismatch 0).

Printed per recording: what was named and the three values with their errors; then, per
parameter, the pulls' mean and standard deviation, how many lie within 3 sigma, and the
scatter of the values over the recordings beside the median error: an error that
describes the fit has pulls of sd ~1 and a scatter equal to its median.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose import diagnose
from hwp_tes_systematics.diagnose.effects.fluctuations import F_REF_HZ


def truths(sigma_drift: float, mismatch: float) -> dict[str, float]:
    """The generator's (a, beta, rho) of litebird_sim's THERMAL_GAIN defaults."""
    import litebird_sim as lbs

    params = lbs.GainDriftParams()
    ratio_t = params.thermal_fluctuation_amplitude_K / params.focalplane_Tbath_K
    beta = params.alpha_drift
    knee = (params.fknee_drift_mHz * 1e-3 / F_REF_HZ) ** (beta / 2)
    return {
        "a": math.sqrt(2) * sigma_drift * ratio_t * knee * (1 + mismatch / 2),
        "beta": beta,
        "rho": 1.0,
    }


def one(support, arguments, seed: int, folder: Path) -> dict:
    """Simulate with nominal errors, apply the thermal drift, diagnose: the fitted values."""
    import litebird_sim as lbs

    started = time.perf_counter()
    rng = np.random.default_rng([seed, 46])
    errors = support.nominal_errors(rng)
    a2 = support.nominal(arguments.channel)["a2_k"]
    recording, _ = support.recorded_with_errors(
        folder, [], 30_000 + seed, errors, hours=arguments.hours, name=f"f{seed}.h5",
        channel=arguments.channel, a2_k=a2,
    )  # fmt: skip
    params = lbs.GainDriftParams(
        drift_type=lbs.GainDriftType.THERMAL_GAIN,
        sigma_drift=arguments.sigma_drift,
        detector_mismatch=arguments.mismatch,
    )
    lbs.apply_gaindrift_to_tod(
        recording.tod,
        recording.sampling_rate_hz,
        params,
        focalplane_attr=np.array(["wafer"] * recording.tod.shape[0]),
        dets_random=[np.random.default_rng(rng.integers(2**32)) for _ in recording.tod],
    )
    result = diagnose(recording, support.supplied_sky(errors), a2, figures=False)
    names = result.effect_names
    fitted = {}
    if "gain_fluctuations" in names:
        for entry in result.effect("gain_fluctuations")["parameters"].values():
            fitted[entry["parameter"]] = (entry["value"], entry["sigma"])
    text = ", ".join(f"{k} {v:.4g} +- {s:.2g}" for k, (v, s) in fitted.items())
    print(
        f"seed {seed}: {', '.join(names) or '-'}; {text or 'no gain_fluctuations'}; "
        f"{time.perf_counter() - started:.0f} s",
        flush=True,
    )
    return {"seed": seed, "named": names, "fitted": fitted}


def summary(records: list[dict], truth: dict[str, float]) -> list[str]:
    """Per parameter: pulls' mean, sd, within 3 sigma; values' scatter against the errors."""
    found = [r for r in records if r["fitted"]]
    lines = [f"gain_fluctuations named in {len(found)} / {len(records)} recordings"]
    for name in ("a", "beta", "rho"):
        pairs = np.array([r["fitted"][name] for r in found if name in r["fitted"]], dtype=float)
        if len(pairs) < 2:
            continue
        values, sigmas = pairs[:, 0], pairs[:, 1]
        pulls = (values - truth[name]) / sigmas
        lines.append(
            f"{name}: truth {truth[name]:.4g}, mean {values.mean():.4g}; pulls mean "
            f"{pulls.mean():+.2f} sd {pulls.std(ddof=1):.2f}, within 3 sigma "
            f"{int(np.sum(np.abs(pulls) < 3))}/{len(pulls)}; scatter {values.std(ddof=1):.3g} "
            f"against median error {np.median(sigmas):.3g}"
        )
    return lines


def main() -> None:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--hours", type=float, default=2.0)
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--first-seed", type=int, default=301)
    parser.add_argument("--sigma-drift", type=float, default=1e-4)
    parser.add_argument("--mismatch", type=float, default=0.0)
    parser.add_argument("--out", type=Path)
    arguments = parser.parse_args()
    from hwp_tes_systematics.diagnose import testbed as support

    truth = truths(arguments.sigma_drift, arguments.mismatch)
    seeds = range(arguments.first_seed, arguments.first_seed + arguments.seeds)
    with tempfile.TemporaryDirectory() as folder:
        records = [one(support, arguments, seed, Path(folder)) for seed in seeds]
    lines = summary(records, truth)
    print("\n".join(lines))
    if arguments.out:
        arguments.out.write_text(
            json.dumps({"arguments": vars(arguments) | {"out": str(arguments.out)},
                        "truth": truth, "records": records, "summary": lines}, indent=1)
        )  # fmt: skip
    sys.stdout.flush()


if __name__ == "__main__":
    main()
