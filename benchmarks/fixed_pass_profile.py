"""Where a fixed TOD pass spends its time, stage by stage, beside each stage's floor: the
numpy, ducc0 or numba primitive it rests on, timed alone at the pass's array sizes.

    python benchmarks/fixed_pass_profile.py                        # config/one_year.yaml's pass
    python benchmarks/fixed_pass_profile.py --nside 512 --variants 512:none --demodulated
    python benchmarks/fixed_pass_profile.py --reference-src ../ref/src   # beside another checkout

The pass is the map-domain fixed pass of one channel (``fixed_maps.fixed_passes``): one
pair, ``--days`` one-day chunks at ``--rate`` Hz, no noise in the TOD, ``--noise-realizations``
reference noise realizations (2, the configurations'), the sky scanned at
``--nside`` with 60 s baselines, plus the map-makers of ``--variants`` (nside:baseline
seconds or none) and, with ``--demodulated``, HWP demodulation at every binned one; one
thread; T_ell and S_ell measured up to ``--measure-lmax`` (the configurations' filter_lmax).
A one-day pass first compiles the kernels and makes the FFT plans of a day's chunk.

Printed, in ns per detector-sample (one sample of one detector): each stage of the pass
(the job's own clock), the floor of that stage, and their ratio; the pass's wall time,
including the solve and the spectra after the chunks (``once per pass``); the FFT
row-samples the pass transforms per detector-sample (forward and inverse each count);
by stage, and the peak memory. With ``--reference-src`` the same pass is run by the package at
that path (another checkout's ``src``, e.g. a worktree at an earlier commit) in its own
process, and its stages are printed beside these.

The floors, per detector-sample, with n the chunk's samples with margins:
- pointing: ducc0's quaternion interpolation and rotation (PointingProvider), ducc0's
  ang2pix and one cos, sin pair per detector, once per direction (a pair shares one);
- sky scan, reference scans: a gather of I, Q, U at the pixels and I + Q c + U s;
- dipole: a dot product of the direction with a velocity per sample;
- noise: a standard normal draw per sample;
- HWPSS, HWPSS moments, nonlinearity terms: one cos (or one product) per sample;
- 2f removal + notch: ducc0's r2c, the notch's product and c2r into preallocated arrays,
  plus the harmonic fit (its templates once), for the rows the pass filters;
- demodulation: the same per row it low-passes (three streams per demodulated row);
- binning: a numba scatter-add of d, d cos 2 alpha, d sin 2 alpha per binned TOD-sample
  (no weights, no matrix: what any binning of the TODs must do).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

STAGES = (
    "pointing",
    "sky scan",
    "dipole",
    "noise",
    "HWPSS",
    "pixels",
    "HWPSS moments",
    "nonlinearity terms",
    "reference scans",
    "2f removal + notch",
    "demodulation",
    "binning",
)


def parse_variant(text: str) -> tuple[int, float | None]:
    nside, baseline = text.split(":")
    return int(nside), None if baseline.lower() == "none" else float(baseline)


def run_pass(arguments) -> dict:
    """Run the fixed pass in this process; returns its figures (see the module docstring)."""
    import ducc0

    sys.path.insert(0, str(Path(__file__).parent))
    from common import run_fixed_pass

    from hwp_tes_systematics import io
    from hwp_tes_systematics.simulation import mapmaking, tod_maps

    if not arguments.default_malloc and hasattr(io, "reuse_freed_memory"):
        io.reuse_freed_memory()
    io.use_threads(1)
    carries_systematics = arguments.channel != "L1-040" and not arguments.no_systematics
    nside, rate = arguments.nside, arguments.rate
    variants = [parse_variant(v) for v in arguments.variants]
    clocks = []

    open_stages = []  # the stages being timed, innermost last

    class RecordedClock(tod_maps.StageClock):  # the pass's own clock, kept
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            clocks.append(self)

        @contextlib.contextmanager
        def __call__(self, stage):
            open_stages.append(stage)
            try:
                with super().__call__(stage):
                    yield
            finally:
                open_stages.pop()

    tod_maps.StageClock = RecordedClock
    transformed = collections.Counter()  # FFT row-samples by stage
    for name in ("r2c", "c2r"):
        original = getattr(ducc0.fft, name)

        def counted(data, *a, _original=original, _name=name, **k):
            n = k.get("lastsize") if _name == "c2r" else np.shape(data)[-1]
            stage = open_stages[-1] if open_stages else "outside the chunks"
            transformed[stage] += np.size(data) // np.shape(data)[-1] * n
            return _original(data, *a, **k)

        setattr(ducc0.fft, name, counted)
    binned = [0]
    original_add = mapmaking.NormalEquations.add

    def counted_add(self, pixels, *a, **k):
        tods = k.get("tods", a[4] if len(a) > 4 else ())
        rows = k.get("rows")
        binned[0] += (len(rows) if rows is not None else len(tods)) * np.size(pixels)
        return original_add(self, pixels, *a, **k)

    mapmaking.NormalEquations.add = counted_add

    def one_pass(days):
        seconds, _, simulator = run_fixed_pass(
            arguments.channel,
            carries_systematics,
            nside,
            rate,
            days,
            measure_lmax=min(3 * nside - 1, arguments.measure_lmax),
            extra_variants=variants,
            demodulated=arguments.demodulated,
            band_limited=arguments.demodulated,
            noise_realizations=arguments.noise_realizations,
        )
        return seconds, simulator

    one_pass(1.0)  # compiles the kernels, makes the day's FFT plans, fills the caches
    clocks.clear()
    transformed.clear()
    binned[0] = 0
    wall_s, simulator = one_pass(arguments.days)
    det_samples = arguments.days * 86400.0 * rate * simulator.n_detectors
    stages = dict(clocks[-1].seconds)
    return {
        "stages_ns": {k: 1e9 * v / det_samples for k, v in stages.items()},
        "wall_s": wall_s,
        "chunks_s": sum(stages.values()),
        "fft_row_samples_per_det_sample": {k: v / det_samples for k, v in transformed.items()},
        "binned_tod_samples_per_det_sample": binned[0] / det_samples,
        "n_detectors": simulator.n_detectors,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "package": __import__("hwp_tes_systematics").__file__,
    }


@numba.njit(nogil=True)
def _scatter_add(pixels, cos, sin, tod, rhs):  # pragma: no cover (compiled)
    """rhs[p] += d [1, c, s] for every sample: one binned TOD's floor."""
    for t in range(pixels.size):
        p = pixels[t]
        rhs[p, 0] += tod[t]
        rhs[p, 1] += tod[t] * cos[t]
        rhs[p, 2] += tod[t] * sin[t]


def best_of(function, repeats=3) -> float:
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - started)
    return best


def floors_ns(arguments, measured: dict) -> dict[str, float]:
    """The floor of each stage, ns per detector-sample (see the module docstring)."""
    import ducc0

    from hwp_tes_systematics.simulation.hwpss_removal import harmonic_templates
    from hwp_tes_systematics.simulation.notch import _transfer_on_rfft_grid, chunk_span

    rate, nside = arguments.rate, arguments.nside
    _, n, _ = chunk_span(0, int(86400 * rate), rate, 1200.0)
    n_det = measured["n_detectors"]
    rng = np.random.default_rng(0)
    per_det = 1e9 / (n * n_det)  # seconds of a chunk-wide call -> ns per detector-sample
    floors = {}
    # pointing, once per direction: quaternion interpolation + rotation, ang2pix, cos/sin
    quaternions = rng.normal(size=(int(n / rate / 60) + 2, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    provider = ducc0.pointingprovider.PointingProvider(0.0, 1 / 60.0, quaternions, 4)
    rotation = np.array([0.0, 0.0, 0.0, 1.0])
    out = np.empty((n, 4))
    base = ducc0.healpix.Healpix_Base(nside, "RING")
    angles = np.stack([np.arccos(rng.uniform(-1, 1, n)), rng.uniform(0, 2 * np.pi, n)], -1)
    psi = rng.uniform(0, 2 * np.pi, n)

    def pointing():
        provider.get_rotated_quaternions(0.0, rate, rotation, out=out)
        base.ang2pix(angles)
        for _ in range(n_det):
            np.cos(psi), np.sin(psi)

    floors["pointing"] = best_of(pointing) * per_det
    maps = rng.normal(size=(3, 12 * nside**2))
    pixels = rng.integers(0, maps.shape[1], n)
    c, s = np.cos(psi), np.sin(psi)

    def scan():
        for _ in range(n_det):
            maps[0, pixels] + maps[1, pixels] * c + maps[2, pixels] * s

    floors["sky scan"] = best_of(scan) * per_det
    references = 2  # the foreground, the reference CMB
    floors["reference scans"] = floors["sky scan"] * references
    vectors, velocity = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    dipole = best_of(lambda: np.einsum("ij,ij->i", vectors, velocity))
    floors["dipole"] = dipole * per_det / n_det  # once per direction
    floors["noise"] = best_of(lambda: rng.standard_normal((n_det, n))) * per_det
    floors["HWPSS"] = best_of(lambda: np.cos(np.broadcast_to(psi, (n_det, n)))) * per_det
    floors["HWPSS moments"] = floors["nonlinearity terms"] = (
        best_of(lambda: np.multiply(np.broadcast_to(psi, (n_det, n)), c)) * per_det
    )
    # the filter: rows of FFTs in preallocated arrays, the harmonic fit
    transforms = measured["fft_row_samples_per_det_sample"]
    fft_rows = max(1, round(transforms.get("2f removal + notch", 0.0) * n_det / 2))
    rows = rng.normal(size=(fft_rows, n))
    spectrum = np.empty((fft_rows, n // 2 + 1), complex)
    filtered = np.empty_like(rows)
    grid = _transfer_on_rfft_grid(n, rate, 0.65, 4 * 0.65 / 100)

    def notch():
        ducc0.fft.r2c(rows, axes=(1,), out=spectrum)
        spectrum.__imul__(grid)
        ducc0.fft.c2r(
            spectrum,
            axes=(1,),
            lastsize=n,
            forward=False,
            inorm=2,
            out=filtered,
            allow_overwriting_input=True,
        )

    chi = np.arange(n) * (2 * np.pi * 0.65 / rate)
    templates = harmonic_templates(chi, (2,), offset=True)

    def fit():
        coefficients = np.linalg.solve(templates @ templates.T, templates @ rows.T)
        rows.__isub__(coefficients.T @ templates)

    notch()  # ducc0's plan
    floors["2f removal + notch"] = (best_of(notch) + best_of(fit)) * per_det
    for length in (n, 65536):  # the chunk's transforms against ones that fit the caches
        block = rng.normal(size=(8, length))
        spectrum_block = np.empty((8, length // 2 + 1), complex)

        def round_trip(block=block, spectrum_block=spectrum_block, length=length):
            ducc0.fft.r2c(block, axes=(1,), out=spectrum_block)
            ducc0.fft.c2r(
                spectrum_block, axes=(1,), lastsize=length, forward=False, inorm=2, out=block
            )

        round_trip()
        seconds = best_of(round_trip)
        floors[f"fft_{length}"] = 1e9 * seconds / block.size / 2
    # the demodulation: a product with 2 cos 4 chi and 2 sin 4 chi, then the low-pass
    # (r2c, product, c2r) of three streams per filtered row: the notch's floor per row
    demodulated_rows = transforms.get("demodulation", 0.0) * n_det / 2
    floors["demodulation"] = floors["2f removal + notch"] * demodulated_rows / fft_rows
    binned_rows = max(1, round(measured["binned_tod_samples_per_det_sample"]))
    tod = rng.normal(size=n)
    rhs = np.zeros((maps.shape[1], 3))
    _scatter_add(pixels, c, s, tod, rhs)  # compiles

    floors["binning"] = (
        best_of(lambda: _scatter_add(pixels, c, s, tod, rhs)) * binned_rows / n * 1e9
    )
    return floors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=2.0, help="one-day chunks")
    parser.add_argument("--rate", type=float, default=19.0, help="sampling rate [Hz]")
    parser.add_argument("--nside", type=int, default=64, help="the scan's and primary nside")
    parser.add_argument("--variants", nargs="*", default=[], help="nside:baseline_s|none")
    parser.add_argument("--demodulated", action="store_true")
    parser.add_argument(
        "--measure-lmax",
        type=int,
        default=128,
        help="T_ell, S_ell measured up to it (simulation.filter_lmax of config/nside*.yaml)",
    )
    parser.add_argument(
        "--noise-realizations",
        type=int,
        default=2,
        help="reference noise realizations (simulation.noise_reference_realizations)",
    )
    parser.add_argument("--no-systematics", action="store_true")
    parser.add_argument("--default-malloc", action="store_true", help="glibc's defaults")
    parser.add_argument("--reference-src", help="another checkout's src, run beside")
    parser.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    measured = run_pass(arguments)
    if arguments.json_only:
        print(json.dumps(measured))
        return
    reference = None
    if arguments.reference_src:
        command = [sys.executable, __file__, *sys.argv[1:], "--json-only"]
        command.remove("--reference-src")
        command.remove(arguments.reference_src)
        environment = os.environ | {"PYTHONPATH": str(Path(arguments.reference_src).resolve())}
        printed = subprocess.run(
            command, check=False, env=environment, capture_output=True, text=True
        )
        if printed.returncode:
            sys.exit(f"the reference pass failed:\n{printed.stderr[-3000:]}")
        reference = json.loads(printed.stdout.strip().splitlines()[-1])
    floors = floors_ns(arguments, measured)
    det_samples = arguments.days * 86400.0 * arguments.rate * measured["n_detectors"]
    print(
        f"{arguments.channel}, {arguments.days:g} days at {arguments.rate:g} Hz, nside "
        f"{arguments.nside}, variants {arguments.variants or 'none'}, demodulated "
        f"{arguments.demodulated}, {arguments.noise_realizations} reference noise "
        f"realizations, one thread ({det_samples:.3g} detector-samples)"
    )
    print(f"package: {measured['package']}")
    header = "| stage | this pass [ns] | floor [ns] | pass / floor |"
    if reference:
        header += " reference pass [ns] | reference / this |"
        print(f"reference: {reference['package']}")
    print(header)
    print("|---" * (header.count("|") - 1) + "|")
    fft_lengths = [key for key in floors if key.startswith("fft_")]
    fft_ns = {int(key[4:]): floors.pop(key) for key in fft_lengths}
    for stage in STAGES:
        ns = measured["stages_ns"].get(stage)
        before = (reference or {}).get("stages_ns", {}).get(stage)
        if ns is None and before is None:
            continue
        ns = ns or 0.0
        floor = floors.get(stage, 0.0)
        ratio = f"{ns / floor:.1f}" if floor > 0 else "-"
        line = f"| {stage} | {ns:.0f} | {floor:.0f} | {ratio} |"
        if reference:
            line += f" {before or 0.0:.0f} | {(before or 0.0) / max(ns, 1e-9):.2f} |"
        print(line)
    rows = [("chunks (the stages)", "chunks_s"), ("whole pass (with the solve)", "wall_s")]
    for label, key in rows:
        ns = 1e9 * measured[key] / det_samples
        line = (
            f"| {label} | {ns:.0f} | {sum(floors.values()):.0f} | {ns / sum(floors.values()):.1f} |"
        )
        if reference:
            before = 1e9 * reference[key] / det_samples
            line += f" {before:.0f} | {before / ns:.2f} |"
        print(line)
    print(
        "ducc0 real FFT, forward or inverse, per row-sample: "
        + ", ".join(f"{ns:.1f} ns at {length:,} samples" for length, ns in fft_ns.items())
    )
    transforms = ", ".join(
        f"{stage} {value:.1f}"
        for stage, value in measured["fft_row_samples_per_det_sample"].items()
    )
    print(
        f"FFT row-samples per detector-sample (forward and inverse each): {transforms}; "
        f"binned TOD-samples per detector-sample "
        f"{measured['binned_tod_samples_per_det_sample']:.1f}; peak RSS "
        f"{measured['peak_rss_mb']:.0f} MB"
        + (f" (reference {reference['peak_rss_mb']:.0f} MB)" if reference else "")
    )


if __name__ == "__main__":
    main()
