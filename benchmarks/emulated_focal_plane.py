"""Focal planes emulated by the map-domain seeds, against the run of the focal plane they
emulate.

    python benchmarks/emulated_focal_plane.py --run 8=n8/results/requirement.json \\
        --emulated 1=e1_to_8/results/requirement.json 2=e2_to_8/results/requirement.json \\
        --emulated 8=e8_to_all/results/requirement.json

A run with ``instrument.emulated_pairs_per_channel: N_e`` simulates N pairs per channel and
scales its seeds' binned noise and g1 draws by sqrt(N / N_e) (config.emulated_pairs_factor).
Each ``--emulated N=path`` is such a run's ``requirement.json`` (N its simulated pairs);
``--run N_e=path`` the run that simulates the N_e pairs the emulations emulate, if there is
one. Prints, per quantity of ``requirement_vs_pairs.QUANTITIES`` (the random population's
68 % point and Fisher reading, the common offset, sigma_r), the two readings that carry the
linear term (the paper's estimator and the fixed instruments'), and the systematic's power k of
its two largest parts (the fixed template's, a detector's noise through the s h term;
``systematic_only.template_split``), each file's value, and for each
emulation its ratio to the run and their difference over the errors added in quadrature
(where both give one; the runs share the CMB and foreground draws, so that error is an
upper bound). An emulation whose N_e is not the run's is printed without a comparison.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from requirement_vs_pairs import QUANTITIES as PAIRS_QUANTITIES

# and the systematic's power k [K^2] of its two largest parts (systematic_only.template_split):
# the fixed pass's template and a detector's own noise through the s h term
SPLIT = "systematic_only", "template_split", "k_per_k2"
QUANTITIES = {
    **PAIRS_QUANTITIES,
    # the readings with the linear term (each seed's sky and noise times the systematic):
    # the paper's estimator, mean |r_sys - r_nosys| over injected seeds, at the budget, and
    # the median over fixed instruments (g1 held over the seeds) of the 68 % point's shift
    "paper's estimator, budget crossing [1/K]": lambda d: (
        d["budget_crossing"]["sigma_g1_per_k"],
        None,
    ),
    "fixed instruments, 68 % point, median [1/K]": lambda d: (
        d["fixed_instruments"]["fraction_point"]["requirement_median_per_k"],
        None,
    ),
    "k, fixed x fixed [K^2]": lambda d: (_split(d)["fixed_x_fixed"], None),
    "k, noise_h x noise_h [K^2]": lambda d: (_split(d)["noise_h_x_noise_h"], None),
}


def _split(data: dict) -> dict:
    return data[SPLIT[0]][SPLIT[1]][SPLIT[2]]


def read(item: str, parser, emulated: bool) -> tuple[int, dict]:
    """(N, requirement.json) of ``N=path``, checking N against the file's settings."""
    n, _, path = item.partition("=")
    if not path:
        parser.error(f"{item!r}: expected N=path/to/requirement.json")
    data = json.loads(Path(path).read_text())
    settings = data["settings"]
    if settings.get("pairs_per_channel") != int(n):
        parser.error(f"{path}: pairs_per_channel is {settings.get('pairs_per_channel')}, not {n}")
    if emulated and settings.get("emulated_pairs_per_channel") is None:
        parser.error(f"{path}: emulates nothing (instrument.emulated_pairs_per_channel null)")
    return int(n), data


def positions(data: dict) -> str:
    """Where the run's detectors point (``instrument.detector_positions``; files made
    before the key: the boresight)."""
    return data["settings"].get("detector_positions", "boresight").replace("_", " ")


def described(data: dict) -> str:
    """The run's sentence (``headline.run``), or its settings in a file made before it,
    after its detectors' positions."""
    return f"detectors at the {positions(data).replace(' ', '-')} positions; " + (
        data["headline"].get("run") or json.dumps(data["settings"])
    )


def comparison(value, error, truth, truth_error) -> str:
    """'ratio r, +x.x sigma' of an emulated value against the run's."""
    text = f"ratio {value / truth:.3f}"
    if error and truth_error:
        text += f", {(value - truth) / math.hypot(error, truth_error):+.1f} sigma"
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", help="N_e=path/to/requirement.json of the run emulated")
    parser.add_argument("--emulated", nargs="+", required=True, help="N=path/to/requirement.json")
    args = parser.parse_args()
    emulations = [read(item, parser, True) for item in args.emulated]
    run = read(args.run, parser, False) if args.run else None
    for n, data in emulations:
        print(f"emulated from N = {n}: {described(data)}")
    if run:
        print(f"run of N = {run[0]}: {described(run[1])}")
    for label, reader in QUANTITIES.items():
        print(label)
        truth, truth_error = reader(run[1]) if run else (None, None)
        if run:
            print(
                f"    run, N = {run[0]}: {truth:.3g}"
                + (f" +- {truth_error:.2g}" if truth_error else "")
            )
        for n, data in emulations:
            value, error = reader(data)
            emulated = data["settings"]["emulated_pairs_per_channel"]
            line = f"    emulated {emulated} from N = {n} ({positions(data)}): {value:.3g}"
            line += f" +- {error:.2g}" if error else ""
            if run and emulated == run[0]:
                line += f" ({comparison(value, error, truth, truth_error)})"
            print(line)


if __name__ == "__main__":
    main()
