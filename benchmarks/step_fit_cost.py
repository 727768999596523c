"""What the readout-step search's exact fit costs: :func:`position_fits` at 1, 3 and 17
positions (a lone step, a step's time refined, a bias line's window) beside a bank of
linear templates, on one detector's hour.

    python benchmarks/step_fit_cost.py
    python benchmarks/step_fit_cost.py --reference-src ../ref/src   # beside another checkout

The detector: ``--hours`` at ``--rate`` Hz (n samples), weights w(f) = 1 / (1 + (f_knee /
f)^alpha) / n (f_knee 50 mHz, alpha 1.5; unit white noise), ``--flagged`` samples flagged at random before the
positions, a 2f carrier as the gain part's signal, a bank of ``--bank`` random templates
plus the linear trend (rfft rows, their Gram matrix precomputed as the selection holds
it), both parts (offset and gain), the positions from sample n / 2 on. Printed per
position count: the best of ``--repeats`` calls in ms (one BLAS thread), and the first
position's delta chi^2 (the same in both checkouts where the fits agree). With
``--reference-src`` the same is run by the package at that path (its
``diagnose.effects.step_fit``, or ``step_search`` where it predates that module) in its
own process, and its figures are printed beside these.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import subprocess
import sys
import time

import numpy as np

POSITION_COUNTS = (1, 3, 17)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=1.0, help="recording length (h)")
    parser.add_argument("--rate", type=float, default=19.0, help="sampling rate (Hz)")
    parser.add_argument("--bank", type=int, default=25, help="linear templates beside the step")
    parser.add_argument("--flagged", type=int, default=100, help="flagged samples")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--reference-src", help="another checkout's src, timed beside this one")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON only")
    return parser.parse_args(argv)


def n_samples(args) -> int:
    return round(args.hours * 3600 * args.rate)


def measure(args) -> dict:
    """Position count -> (best time in ms, first delta chi^2), in this process."""
    from hwp_tes_systematics.diagnose.fourier import rfft
    from hwp_tes_systematics.diagnose.linalg import cross

    try:
        from hwp_tes_systematics.diagnose.effects import step_fit as module
    except ImportError:  # a checkout before the exact fit had its own module
        from hwp_tes_systematics.diagnose.effects import step_search as module
    from hwp_tes_systematics.diagnose.effects.step_scan import trend

    rng = np.random.default_rng(1)
    n = n_samples(args)
    freqs = np.fft.rfftfreq(n, 1.0 / args.rate)
    w = 1.0 / (n * (1.0 + (0.05 / np.maximum(freqs, freqs[1])) ** 1.5))  # unit white noise
    valid = np.ones(n, bool)
    valid[rng.choice(n // 2, size=args.flagged, replace=False)] = False
    times_s = np.arange(n) / args.rate
    signal = 0.2 * np.cos(2 * np.pi * 1.3 * times_s)  # a 2f line, K
    rows = rfft(rng.standard_normal((args.bank, n)) * valid)
    trend_f = rfft(trend(n) * valid)
    r_f = rfft(rng.standard_normal(n) * valid)
    of = module.Bank.of
    extra = {"n": n} if "n" in inspect.signature(of).parameters else {}
    figures = {}
    for count in POSITION_COUNTS:
        positions = list(range(n // 2, n // 2 + count))
        best = np.inf
        for _ in range(args.repeats):
            bank = of(rows, cross(rows, rows, w), trend_f, w, **extra)  # fresh: no caches
            start = time.perf_counter()
            fits = module.position_fits(r_f, w, valid, signal, positions, bank, ("offset", "gain"))
            best = min(best, time.perf_counter() - start)
        first = fits[0]
        delta = first.delta_chi2 if hasattr(first, "delta_chi2") else first[0]
        figures[count] = (1e3 * best, float(delta))
    return figures


def main(argv=None):
    args = parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    here = measure(args)
    if args.json:
        print(json.dumps({str(k): v for k, v in here.items()}))
        return
    reference = None
    if args.reference_src:
        command = [sys.executable, __file__, "--json"] + [
            a for a in (argv if argv is not None else sys.argv[1:]) if "reference-src" not in a
        ]
        command = [c for c in command if c != args.reference_src]
        environment = dict(os.environ, PYTHONPATH=args.reference_src, OMP_NUM_THREADS="1")
        out = subprocess.run(command, env=environment, capture_output=True, text=True, check=True)
        reference = {int(k): v for k, v in json.loads(out.stdout.splitlines()[-1]).items()}
    n = n_samples(args)
    print(
        f"position_fits, both parts, a bank of {args.bank} templates + the trend, "
        f"n = {n:,} samples, {args.flagged} flagged; best of {args.repeats}"
    )
    header = f"{'positions':>9}  {'this (ms)':>10}  {'delta chi2':>12}"
    if reference:
        header += f"  {'reference (ms)':>14}  {'ratio':>6}  {'its delta chi2':>14}"
    print(header)
    for count, (ms, delta) in here.items():
        line = f"{count:>9}  {ms:>10.1f}  {delta:>12.6g}"
        if reference:
            ref_ms, ref_delta = reference[count]
            line += f"  {ref_ms:>14.1f}  {ref_ms / ms:>6.2f}  {ref_delta:>14.6g}"
        print(line)


if __name__ == "__main__":
    main()
