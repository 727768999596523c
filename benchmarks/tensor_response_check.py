"""Does the tensor probe give the map's response to r? Two runs of the same seeds, one with r.

    python benchmarks/tensor_response_check.py R_RUN/results R0_RUN/results --r 0.03

The map-domain seeds' B modes alone at r and at r = 0 share their random phases, and the
recovered B modes' power is linear in the input spectrum, so the mean over seeds of
C(recovered B modes alone, r) - C(recovered B modes alone, 0) is what r C_GW adds to the
map, free of noise and foregrounds. Per bin of ell, prints it over the two responses a
model can use: r R_ell C_GW (R_ell of the tensor probe, ``tensor_response_bb`` of the
r = 0 run's noise model) and r P_ell C_GW (P_ell of the lensing B modes,
``sky_b_power_transfer_bb``), with the error of the first from both means over seeds (the
added power scales each seed's own lensing B realization, so it has cosmic variance
too). A response that describes the map gives 1.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from hwp_tes_systematics import sky

BINS = ((2, 4), (5, 10), (11, 20), (21, 40), (41, 80), (81, 128))
COLUMN = "bb_cmb_recovered_b_only_k2"


def per_seed(results: Path, column: str) -> dict[str, np.ndarray]:
    """{seed folder: ``column`` of its ``nosys.csv``} of the run's seeds."""
    tables = sorted((results / "spectra").glob("seed*/nosys.csv"))
    if not tables:
        raise SystemExit(f"{results}: no spectra/seed*/nosys.csv")
    return {path.parent.name: pd.read_csv(path)[column].to_numpy() for path in tables}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("with_r", type=Path, help="results/ of the run with r")
    parser.add_argument("without_r", type=Path, help="results/ of the same seeds at r = 0")
    parser.add_argument("--r", type=float, required=True, help="the r of the first run")
    args = parser.parse_args()
    with_r, without_r = per_seed(args.with_r, COLUMN), per_seed(args.without_r, COLUMN)
    if sorted(with_r) != sorted(without_r):
        raise SystemExit("the two runs do not hold the same seeds")
    added_per_seed = np.array([with_r[seed] - without_r[seed] for seed in sorted(with_r)])
    added = added_per_seed.mean(axis=0)
    noise = pd.read_csv(args.without_r / "spectra" / "noise_model.csv")
    c_gw = sky.tensor_bb_r1(len(noise) - 1)
    probe = args.r * noise["tensor_response_bb"].to_numpy() * c_gw
    probe_sem = args.r * noise["tensor_response_bb_sem"].to_numpy() * c_gw
    lensing_b = args.r * noise["sky_b_power_transfer_bb"].to_numpy() * c_gw
    print("ell  added by r [K^2]  added / r R C_GW (probe) +- error  added / r P C_GW")
    for first, last in BINS:
        s = slice(first, last + 1)
        ratio = added[s].sum() / probe[s].sum()
        # the seeds' own sky (the added power scales each seed's lensing B realization)
        # and the probe's mean, in quadrature
        binned = added_per_seed[:, s].sum(axis=1)
        added_error = binned.std(ddof=1) / np.sqrt(len(binned)) / binned.mean()
        probe_error = np.sqrt(np.sum(probe_sem[s] ** 2)) / probe[s].sum()
        error = ratio * np.hypot(added_error, probe_error)
        print(
            f"{first}-{last}  {added[s].mean():.3e}  {ratio:.3f} +- {error:.3f}  "
            f"{added[s].sum() / lensing_b[s].sum():.3f}"
        )


if __name__ == "__main__":
    main()
