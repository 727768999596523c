"""r read on one run's maps through another run's model: the tensor transfer tested where it can fail.

    python benchmarks/r_readback_across_runs.py R_RUN/results R0_RUN/results --r 0.03

A run's own ``consistency -> r_recovery`` reads r with a model whose CMB terms were
measured on the same seeds, r included, so it returns r by construction. Here the model
is the r = 0 run's (``R0_RUN/results/spectra/noise_model.csv``: noise, foreground
residual, lensing transfer measured without tensors, the tensor term from the probe),
and the data are the r > 0 run's HILC maps (``bb_recovered_k2`` of every
``spectra/seed*/nosys.csv``). Nothing of the r > 0 maps entered the model, so a wrong
tensor response moves r read back by its own ratio. Prints, per likelihood model
(:data:`hwp_tes_systematics.analysis.noise_model.ANALYSES` with a transfer), r's mean over
seeds with its standard error and the pull from the input, for all seeds and for the
held-out halves (model from the even seeds of the r = 0 run, data from the odd seeds of
the r run, and the other way), whose noise realizations differ too; a half's standard
error adds, in quadrature, the model half's own (r read through the model on the r = 0
seeds it was measured on), as ``consistency.held_out_r_recovery`` does.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from hwp_tes_systematics.analysis.consistency import check_r_recovery
from hwp_tes_systematics.analysis.noise_model import measure, model_from_noise_table

ANALYSES = ("transfer_in_model", "recovered_power")


def seed_tables(results: Path) -> dict[str, pd.DataFrame]:
    """{seed folder: its ``nosys.csv``} of the run's seeds, in seed order."""
    tables = {p.parent.name: p for p in (results / "spectra").glob("seed*/nosys.csv")}
    if not tables:
        raise SystemExit(f"{results}: no spectra/seed*/nosys.csv")
    order = sorted(tables, key=lambda name: int(name.removeprefix("seed")))
    return {name: pd.read_csv(tables[name]) for name in order}


def read_back(noise: pd.DataFrame, data: list[pd.DataFrame], r_input, lmin, lmax) -> dict:
    """{analysis: check_r_recovery of ``data``'s HILC maps through ``noise``'s model}."""
    recovered = np.array([t["bb_recovered_k2"].to_numpy()[: lmax + 1] for t in data])
    out = {}
    for analysis in ANALYSES:
        model = model_from_noise_table(noise, lmin, lmax, analysis)
        out[analysis] = check_r_recovery(model, recovered, r_input)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("with_r", type=Path, help="results/ of the run with r")
    parser.add_argument("without_r", type=Path, help="results/ of a run at r = 0")
    parser.add_argument("--r", type=float, required=True, help="the r of the first run")
    parser.add_argument("--lmin", type=int, default=2, help="likelihood lmin (config)")
    parser.add_argument("--lmax", type=int, default=128, help="likelihood lmax (config)")
    args = parser.parse_args()
    with_r, without_r = seed_tables(args.with_r), seed_tables(args.without_r)
    noise = pd.read_csv(args.without_r / "spectra" / "noise_model.csv")
    rows = []
    everything = read_back(noise, list(with_r.values()), args.r, args.lmin, args.lmax)
    rows += [("all seeds", a, res) for a, res in everything.items()]
    names = list(without_r)
    halves = {"even": names[0::2], "odd": names[1::2]}
    for model_half, data_half in (("even", "odd"), ("odd", "even")):
        model_seeds = [without_r[n] for n in halves[model_half]]
        model_noise = measure(model_seeds)
        data = [with_r[n] for n in halves[data_half] if n in with_r]
        split = read_back(model_noise, data, args.r, args.lmin, args.lmax)
        # the model half's own scatter: r read on its seeds (r = 0) through it
        own = read_back(model_noise, model_seeds, 0.0, args.lmin, args.lmax)
        for analysis, res in split.items():
            res["r_sem"] = float(np.hypot(res["r_sem"], own[analysis]["r_sem"]))
        label = f"model {model_half} (r = 0), data {data_half} (r)"
        rows += [(label, a, res) for a, res in split.items()]
    print(f"r input {args.r:g}; model from {args.without_r}, maps from {args.with_r}")
    print(f"{'seeds':38s} {'model':18s} {'r read back':>12s} {'+- sem':>9s} {'pull':>6s} n")
    for label, analysis, res in rows:
        print(
            f"{label:38s} {analysis:18s} {res['r_mean']:12.5f} {res['r_sem']:9.5f} "
            f"{(res['r_mean'] - args.r) / res['r_sem']:6.2f} {res['n_seeds']}"
        )
    print("per bin, all seeds, recovered_power: data / model at r input")
    for row in everything["recovered_power"]["bins"]:
        print(f"  ell {row['ell'][0]:3d}-{row['ell'][1]:3d}  {row['data_over_model']:.3f}")


if __name__ == "__main__":
    main()
