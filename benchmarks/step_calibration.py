"""Are a readout step's significance, values and time errors what they say? Simulated steps.

    python benchmarks/step_calibration.py --draws 300 --out step_calibration.json
    python benchmarks/step_calibration.py --draws 300 --gap-fraction 0.02   # with a gap

Each draw: one detector's 1/f + white noise (white 2e-4 K per sample at 19 Hz, knee
``--knees`` [Hz], slope 1.5, the weights its PSD) recorded for ``--seconds`` out of a
stream four times as long, so that, as in a real recording, the noise does not come back
at the end to where it started (a periodic draw would); a 2f HWPSS carrier of 0.2 K; with
``--gap-fraction`` that fraction of the samples flagged in one gap starting a third of the
way through (the residual zero there, as the diagnosis's is). Then:

- **noise alone**: the offset step's z = <T, R> / sqrt(<T, T>) at 3 fixed times (a sixth,
  half and five sixths of the way through: before and after a gap), fitted alone in the
  periodic residual and beside the scan's nuisance templates (the linear trend, and the
  gap offset with a gap): a calibrated z has a spread of 1;
- **a step**: an offset or a gain step (half each) of 5-50 sigma (log-uniform) at a random
  time, searched for (:func:`find_steps`, ln N of the recording): found or not, its part,
  the pull of its value and of its time (over its error), and its sharpness verdict.

Printed: the z spreads and the fraction beyond 4, then per part the steps found, the
pulls' sd and fraction within 3, and the time pulls' fractions within 0.5, 1 and 3.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose.effects.step_scan import edge_shape, scan_parts
from hwp_tes_systematics.diagnose.effects.step_search import StepSearch, find_steps
from hwp_tes_systematics.diagnose.fourier import rfft
from hwp_tes_systematics.diagnose.linalg import cross

FS_HZ = 19.0
F_HWP_HZ = 46 / 60
A2_K = 0.2
WHITE_K = 2e-4  # per sample
ALPHA = 1.5
STREAM_FACTOR = 4  # the stream the recording is cut from, in recording lengths


def psd(n: int, fknee_hz: float) -> np.ndarray:
    """The noise PSD in rfft units (E|X_f|^2) at n samples, DC left out."""
    freqs = np.fft.rfftfreq(n, 1 / FS_HZ)
    out = n * WHITE_K**2 * (1 + (fknee_hz / np.maximum(freqs, 1e-12)) ** ALPHA)
    out[0] = 0.0
    return out


def recorded_noise(rng, n: int, fknee_hz: float) -> np.ndarray:
    """n samples of a stream STREAM_FACTOR times longer: noise that does not wrap."""
    long = STREAM_FACTOR * n
    spectrum = np.sqrt(psd(long, fknee_hz) / 2)
    draw = spectrum * (rng.normal(size=spectrum.size) + 1j * rng.normal(size=spectrum.size))
    return np.fft.irfft(draw, n=long)[:n]


def weights(n: int, fknee_hz: float) -> np.ndarray:
    w = np.zeros(n // 2 + 1)
    s = psd(n, fknee_hz)
    w[1:-1] = 1 / s[1:-1]
    return w


def gap_mask(n: int, fraction: float) -> np.ndarray:
    """The valid samples: one gap of ``fraction`` of them starting at n / 3."""
    valid = np.ones(n, bool)
    valid[n // 3 : n // 3 + int(fraction * n)] = False
    return valid


def noise_z(rng, n: int, fknee_hz: float, carrier_k, valid) -> tuple[list, list]:
    """The offset's z at 3 fixed times on noise alone: (fitted alone, beside the trend)."""
    w = weights(n, fknee_hz)
    r_f = rfft(recorded_noise(rng, n, fknee_hz) * valid)
    scan = scan_parts(r_f, w, valid, carrier_k, 1.0)
    alone, beside = [], []
    for index in (n // 6, n // 2, 5 * n // 6):
        step_f = rfft(edge_shape(n, index) * valid)
        norm = cross(step_f[None], step_f, w)[0]
        alone.append(float(cross(step_f[None], r_f, w)[0] / math.sqrt(norm)))
        inverse = scan.norms.inverse_norms["offset"][index]
        beside.append(float(scan.offset[index] * math.sqrt(inverse)))
    return alone, beside


def one_step(rng, n: int, fknee_hz: float, search: StepSearch, signal) -> dict:
    """A step of 5-50 sigma (its sigma beside the trend) at a random time, searched for."""
    part = str(rng.choice(["offset", "gain"]))
    sigmas = float(np.exp(rng.uniform(math.log(5), math.log(50))))
    first = int(rng.uniform(0.15, 0.85) * n)
    while not search.valid[first]:  # a step's first sample is a recorded one
        first = int(rng.uniform(0.15, 0.85) * n)
    norms = search.norms
    unit = math.sqrt(norms.inverse_norms[part][first])  # the part's sigma per unit value
    value = float(rng.choice([-1, 1])) * sigmas * unit
    shape = edge_shape(n, first) * (1.0 if part == "offset" else signal)
    r_f = rfft((recorded_noise(rng, n, fknee_hz) + value * shape) * search.valid)
    found = find_steps(r_f, search, 0, math.log(2 * n))
    record = {"part": part, "sigmas": sigmas, "knee_hz": fknee_hz, "found": len(found)}
    if found:
        event = min(found, key=lambda e: abs(e.time_s - first / FS_HZ))
        fitted = event.offset_k if part == "offset" else event.gain
        sigma = event.sigma_offset_k if part == "offset" else event.sigma_gain
        record |= {
            "parts": list(event.parts),
            "pull": (fitted - value) / sigma if sigma > 0 else None,
            "time_pull": (event.time_s - first / FS_HZ) / event.sigma_time_s,
            "sharp": event.sharp,
        }
    return record


def summary(noise: dict, steps: list[dict]) -> list[str]:
    lines = []
    for name, z in noise.items():
        z = np.asarray(z)
        lines.append(
            f"noise alone, offset z {name}: sd {z.std():.2f} over {z.size}, "
            f"beyond 4: {np.mean(np.abs(z) > 4):.3f}"
        )
    for part in ("offset", "gain"):
        rows = [s for s in steps if s["part"] == part]
        found = [s for s in rows if s["found"]]
        pulls = np.array([s["pull"] for s in found if s.get("pull") is not None])
        times = np.abs([s["time_pull"] for s in found])
        right = sum(s["parts"] == [part] for s in found)
        lines.append(
            f"{part} steps: found {len(found)}/{len(rows)} (that part alone {right}); "
            f"value pulls sd {pulls.std():.2f}, within 3: {np.mean(np.abs(pulls) < 3):.3f}; "
            f"times within 0.5, 1, 3 of their error: {np.mean(times < 0.5):.2f}, "
            f"{np.mean(times < 1):.2f}, {np.mean(times < 3):.3f}; "
            f"sharp {sum(s['sharp'] for s in found)}/{len(found)}"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--draws", type=int, default=300, help="steps (and noise draws) per knee")
    parser.add_argument("--seconds", type=float, default=1200.0, help="recording length [s]")
    parser.add_argument("--knees", nargs="+", type=float, default=[0.02, 0.1], help="[Hz]")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--gap-fraction", type=float, default=0.0, help="samples flagged in one gap (0-0.5)"
    )
    parser.add_argument("--out", type=Path)
    arguments = parser.parse_args()
    n = int(arguments.seconds * FS_HZ)
    if not 0 <= arguments.gap_fraction <= 0.5:
        parser.error(f"--gap-fraction {arguments.gap_fraction}: expected 0 to 0.5")
    valid = gap_mask(n, arguments.gap_fraction)
    times_s = np.arange(n) / FS_HZ
    signal = A2_K * np.cos(4 * np.pi * F_HWP_HZ * times_s)
    start = time.monotonic()
    noise: dict[str, list] = {"alone": [], "beside the nuisance templates": []}
    steps = []
    for index, knee in enumerate(arguments.knees):
        rng = np.random.default_rng([arguments.seed, index])
        w = weights(n, knee)
        search = StepSearch.of(w, valid, signal, times_s, F_HWP_HZ)
        for draw in range(arguments.draws):
            alone, beside = noise_z(rng, n, knee, search.norms.carrier_k, valid)
            noise["alone"] += alone
            noise["beside the nuisance templates"] += beside
            steps.append(one_step(rng, n, knee, search, signal))
            if (draw + 1) % 50 == 0:
                print(f"knee {knee} Hz: {draw + 1} draws", file=sys.stderr, flush=True)
    print("\n".join(summary(noise, steps)))
    print(f"{time.monotonic() - start:.0f} s")
    if arguments.out:
        arguments.out.write_text(json.dumps({"noise": noise, "steps": steps}, indent=1) + "\n")


if __name__ == "__main__":
    main()
