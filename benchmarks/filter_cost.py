"""Where the fixed pass's filter time goes: the HWP-harmonic removal and the 4 f_HWP notch
of one chunk, per row-sample.

    python benchmarks/filter_cost.py --rate 19 --rows 14

One day with its 1200 s margins (the fixed pass's chunk; the FFT length chunk_span picks)
of ``--rows`` TOD rows (M1-140's fixed pass with calibration: 7 TODs x 2 detectors), one
thread, best of three: the harmonic templates (cos, sin 2 chi and a constant), the fit of
their coefficients, their subtraction, the forward real FFT, the notch's multiplication,
the inverse FFT. Printed in ns per row-sample (a row-sample is one sample of one TOD row).
"""

from __future__ import annotations

import argparse
import time

import ducc0
import numpy as np

from hwp_tes_systematics.simulation import notch
from hwp_tes_systematics.simulation.hwpss_removal import harmonic_templates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=19.0, help="sampling rate [Hz]")
    parser.add_argument("--rows", type=int, default=14)
    parser.add_argument("--f-hwp", type=float, default=0.65, help="HWP frequency [Hz] (MFT)")
    arguments = parser.parse_args()
    rate, f_hwp = arguments.rate, arguments.f_hwp
    _, n, _ = notch.chunk_span(0, int(86400 * rate), rate, 1200.0)
    rows = np.random.default_rng(0).normal(size=(arguments.rows, n))
    chi = 2 * np.pi * f_hwp * np.arange(n) / rate
    grid = notch._transfer_on_rfft_grid(n, rate, f_hwp, 4 * f_hwp / 100)
    best: dict[str, float] = {}
    for _ in range(3):
        tod = rows.copy()
        times = {}
        clock = time.perf_counter()

        def lap(name, times=times):
            nonlocal clock
            now = time.perf_counter()
            times[name] = now - clock
            clock = now

        templates = harmonic_templates(chi, (2,), offset=True)
        lap("harmonic templates")
        coefficients = np.linalg.solve(templates @ templates.T, templates @ tod.T)
        lap("their coefficients")
        for row, row_coefficients in zip(tod, coefficients.T, strict=True):
            row -= row_coefficients @ templates
        lap("their subtraction")
        spectrum = ducc0.fft.r2c(tod, axes=(1,))
        lap("forward FFT")
        spectrum *= grid
        lap("notch multiplication")
        ducc0.fft.c2r(
            spectrum, axes=(1,), lastsize=n, forward=False, inorm=2, allow_overwriting_input=True
        )
        lap("inverse FFT")
        for name, seconds in times.items():
            best[name] = min(best.get(name, np.inf), seconds)
    size = rows.size
    print(f"{arguments.rows} rows x {n} samples ({rate:g} Hz, one day + margins), one thread")
    for name, seconds in best.items():
        print(f"  {name:22s} {seconds / size * 1e9:5.1f} ns per row-sample")
    total = sum(best.values())
    fft = best["forward FFT"] + best["inverse FFT"]
    print(f"  {'total':22s} {total / size * 1e9:5.1f} ns per row-sample, FFTs {fft / total:.0%}")


if __name__ == "__main__":
    main()
