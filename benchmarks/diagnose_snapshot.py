"""Diagnoses of a fixed set of recordings, written as JSON: a before/after check of the engine.

    python benchmarks/diagnose_snapshot.py --out /tmp/before
    ... change the diagnosis code ...
    python benchmarks/diagnose_snapshot.py --out /tmp/after
    python benchmarks/same_results.py /tmp/before /tmp/after

One recording per way a simulated recording can carry an effect (each injection stage of
:func:`hwp_tes_systematics.diagnose.simulate.simulate_recording`: a moved pointing, the
optical signal, the noise, a time constant on signal and noise, the detector's response,
events, effects outside the catalog, effects on the true HWPSS with nominal errors) and a
clean one, each with its own noise seed, two hours of M1-140, nside 32
(:mod:`hwp_tes_systematics.diagnose.testbed`). Writes ``<case>.json`` (the diagnosis) and
``<case>_injected.json`` (the truth) per case; prints the effects each diagnosis names.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose import testbed

CASES = {
    "clean": [],
    "nonlinearity": [("tes_nonlinearity", {"g1": -0.05})],
    "electrothermal": [
        ("tes_electrothermal", {"p0_w": testbed.P0_W, "kelvin_per_watt": testbed.KELVIN_PER_WATT})
    ],
    "time_constant_through_noise": [
        ("detector_time_constant", {"tau": 6e-3, "through_noise": True})
    ],
    "pointing_offset": [("pointing_offset", {"offset_x": 3.0, "offset_y": -2.0})],
    "glitches": [("glitches", {"events": [(0, 1800.0, 4e-3, 0.1), (1, 4000.0, 3e-3, 0.2)]})],
    "noise_mismatch": [("noise_mismatch", {"net_ukrts": 60.0, "fknee_mhz": 50.0})],
    "harmonic_and_gain": [
        ("hwpss_harmonics", {"c4": 2e-4, "s4": -1e-4}),
        ("gain_drift", {"g1": 3e-3}),
    ],
    "crosstalk": [("crosstalk", {"x": 0.01})],
    "pickup_line": [("pickup_line", {"amplitude_k": 3e-4, "freq_hz": 2.345})],
    "spin_modulation": [("hwpss_spin_modulation", {"amplitude_k": 2e-4, "harmonic": 3})],
}
# recordings with random nominal errors, on the true HWPSS (testbed.recorded_with_errors)
CASES_WITH_ERRORS = {
    "errors_sine_modulation": [("hwpss_sine_modulation", {"relative": 0.02, "period_s": 900.0})],
    "errors_temperature_drift": [("hwp_temperature_drift", {"c1": 3e-4})],
    "errors_nonlinearity": [("tes_nonlinearity", {"g1": -0.05})],
}


def _plain(value):
    """Arrays and numbers of numpy as JSON values."""
    return value.tolist() if hasattr(value, "tolist") else repr(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the JSON files")
    parser.add_argument("--only", nargs="*", help="some of the cases")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cases = {**CASES, **CASES_WITH_ERRORS}
    for seed, (case, effects) in enumerate(cases.items(), start=9100):
        if args.only and case not in args.only:
            continue
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            if case in CASES_WITH_ERRORS:
                errors = testbed.nominal_errors(np.random.default_rng(seed))
                recording, injected = testbed.recorded_with_errors(Path(tmp), effects, seed, errors)
            else:
                recording, injected = testbed.recorded(Path(tmp), effects, seed)
            diagnosis = testbed.run(recording, figures=False)
        (args.out / f"{case}.json").write_text(diagnosis.to_json())
        (args.out / f"{case}_injected.json").write_text(json.dumps(injected, default=_plain))
        print(
            f"{case:32s} {time.perf_counter() - start:6.1f} s  found: "
            f"{', '.join(diagnosis.effect_names) or '-'}",
            flush=True,
        )


if __name__ == "__main__":
    main()
