"""The terms of the r-recovery check's BB, model against data, from runs' seed spectra.

    python benchmarks/r_recovery_terms.py n1/results n2/results

For each run's ``results/`` folder (a map-domain run with the seeds' spectra
``spectra/seed*/nosys.csv`` and ``spectra/noise_model.csv``) and bins of ell, prints the
input CMB's pseudo-BB over the theory C_lens (above 1: the mask's E-to-B leakage, which
the pseudo-C_ell estimator keeps), the model's CMB term (``sky_power_transfer_bb`` x
C_lens, the ``recovered_power`` model's r = 0 CMB, with the HILC's chance correlation
of the CMB and the residual where the noise model holds it) over the data's (the seeds'
mean recovered CMB BB), the data's CMB share of its total BB, and the model's total (CMB
+ N_ell + C_FGres, + the noise x foreground cross term where measured) over the data's:
what the r read on the no-systematics maps sees.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from hwp_tes_systematics import sky

BINS = ((21, 40), (41, 80), (81, 128))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", type=Path, help="runs' results/ folders")
    args = parser.parse_args()
    print("run  ell  input/C_lens  model CMB/data CMB  data CMB/data total  model/data total")
    for results in args.results:
        noise = pd.read_csv(results / "spectra" / "noise_model.csv")
        seeds = sorted((results / "spectra").glob("seed*/nosys.csv"))
        if not seeds:
            parser.error(f"{results}: no spectra/seed*/nosys.csv")
        tables = [pd.read_csv(path) for path in seeds]

        c_lens = sky.lensing_bb(int(noise["ell"].iloc[-1]))
        data, cmb, cmb_input = (
            np.mean([table[c].to_numpy() for table in tables], axis=0)
            for c in ("bb_recovered_k2", "bb_cmb_recovered_k2", "bb_cmb_input_k2")
        )
        model_cmb = noise["sky_power_transfer_bb"].to_numpy() * c_lens
        model = model_cmb + noise["n_ell_bb_k2"].to_numpy() + noise["c_fg_res_bb_k2"].to_numpy()
        if "noise_x_foreground_bb_k2" in noise:  # the HILC's chance correlation, where measured
            model = model + noise["noise_x_foreground_bb_k2"].to_numpy()
        for first, last in BINS:
            s = slice(first, last + 1)
            print(
                f"{results}  {first}-{last}  {cmb_input[s].sum() / c_lens[s].sum():.2f}  "
                f"{model_cmb[s].sum() / cmb[s].sum():.3f}  {cmb[s].sum() / data[s].sum():.3f}  "
                f"{model[s].sum() / data[s].sum():.3f}"
            )


if __name__ == "__main__":
    main()
