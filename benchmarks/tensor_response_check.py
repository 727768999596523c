"""Does the tensor probe give the map's response to r? Two runs of the same seeds, one with r.

    python benchmarks/tensor_response_check.py R_RUN/results R0_RUN/results --r 0.03

The map-domain seeds' B modes alone at r and at r = 0 share their random phases, and the
recovered B modes' power is linear in the input spectrum, so the mean over seeds of
C(recovered B modes alone, r) - C(recovered B modes alone, 0) is what r C_GW adds to the
map, free of noise and foregrounds. Per bin of ell, prints it over the two responses a
model can use: r R_ell C_GW (R_ell of the tensor probe, ``tensor_response_bb`` of the
r = 0 run's noise model, with the error of the probe's mean over seeds) and r P_ell C_GW
(P_ell of the lensing B modes, ``sky_b_power_transfer_bb``). A response that describes
the map gives 1.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from hwp_tes_systematics import sky

BINS = ((2, 10), (11, 20), (21, 40), (41, 80), (81, 128))
COLUMN = "bb_cmb_recovered_b_only_k2"


def seed_mean(results: Path, column: str) -> np.ndarray:
    """Mean over the run's seeds of ``column`` of their ``nosys.csv``."""
    tables = sorted((results / "spectra").glob("seed*/nosys.csv"))
    if not tables:
        raise SystemExit(f"{results}: no spectra/seed*/nosys.csv")
    return np.mean([pd.read_csv(path)[column].to_numpy() for path in tables], axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("with_r", type=Path, help="results/ of the run with r")
    parser.add_argument("without_r", type=Path, help="results/ of the same seeds at r = 0")
    parser.add_argument("--r", type=float, required=True, help="the r of the first run")
    args = parser.parse_args()
    added = seed_mean(args.with_r, COLUMN) - seed_mean(args.without_r, COLUMN)
    noise = pd.read_csv(args.without_r / "spectra" / "noise_model.csv")
    c_gw = sky.tensor_bb_r1(len(noise) - 1)
    probe = args.r * noise["tensor_response_bb"].to_numpy() * c_gw
    probe_sem = args.r * noise["tensor_response_bb_sem"].to_numpy() * c_gw
    lensing_b = args.r * noise["sky_b_power_transfer_bb"].to_numpy() * c_gw
    print("ell  added by r [K^2]  added / r R C_GW (probe) +- probe's error  added / r P C_GW")
    for first, last in BINS:
        s = slice(first, last + 1)
        ratio = added[s].sum() / probe[s].sum()
        error = ratio * np.sqrt(np.sum(probe_sem[s] ** 2)) / probe[s].sum()
        print(
            f"{first}-{last}  {added[s].mean():.3e}  {ratio:.3f} +- {error:.3f}  "
            f"{added[s].sum() / lensing_b[s].sum():.3f}"
        )


if __name__ == "__main__":
    main()
