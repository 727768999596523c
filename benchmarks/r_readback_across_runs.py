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

Then the response, from the same seeds' maps at r and at 0, which share their noise and
foreground realizations: per seed, the difference of r read on the two maps through the
model (one Newton step from the same r, so linear in the spectra), over r; and per bin of
ell, the power r adds (mean over seeds of the difference of the two maps' BB) over the
model's r C_GW term, with the bin's share of the Fisher information. 1 where the model's
response is the map's; the paired differences remove each seed's noise and the model
half's offset.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from hwp_tes_systematics.analysis.consistency import check_r_recovery
from hwp_tes_systematics.analysis.likelihood import linear_r_estimate
from hwp_tes_systematics.analysis.noise_model import measure, model_from_noise_table

ANALYSES = ("transfer_in_model", "recovered_power")
BINS = ((2, 4), (5, 10), (11, 20), (21, 40), (41, 80), (81, 128))


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
    parser.add_argument(
        "--measure-model",
        action="store_true",
        help="measure the r = 0 model from the run's seed tables (noise_model.measure), not "
        "its noise_model.csv: for seeds added to a run without its requirement",
    )
    args = parser.parse_args()
    with_r, without_r = seed_tables(args.with_r), seed_tables(args.without_r)
    if args.measure_model:
        noise = measure(list(without_r.values()))
    else:
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
    paired = [seed for seed in with_r if seed in without_r]
    print_response(noise, with_r, without_r, paired, args)
    for model_half, data_half in (("even", "odd"), ("odd", "even")):
        model_noise = measure([without_r[n] for n in halves[model_half]])
        seeds = [n for n in halves[data_half] if n in with_r]
        print(f"model {model_half} (r = 0), data {data_half}:", end=" ")
        print_response(model_noise, with_r, without_r, seeds, args, per_bin=False)


def print_response(noise, with_r, without_r, seeds, args, per_bin=True) -> None:
    """The model's response against the map's, from paired seeds (module docstring)."""
    lmax = args.lmax
    maps = {
        label: np.array([runs[n]["bb_recovered_k2"].to_numpy()[: lmax + 1] for n in seeds])
        for label, runs in (("r", with_r), ("0", without_r))
    }
    for analysis in ANALYSES:
        model = model_from_noise_table(noise, args.lmin, lmax, analysis)
        read = {
            label: np.array([linear_r_estimate(row, model, args.r) for row in rows])
            for label, rows in maps.items()
        }
        ratio = (read["r"] - read["0"]) / args.r
        sem = ratio.std(ddof=1) / np.sqrt(ratio.size)
        print(f"{analysis}: (r read at r - at 0) / r = {ratio.mean():.3f} +- {sem:.3f}", end="; ")
        if not per_bin:
            continue
        added = maps["r"] - maps["0"]
        information = model.fisher_terms(args.r)
        ell_used = model.ell[model.mask]
        print(f"\n  ell      added / model's r C_GW +- error  share of information ({analysis})")
        for first, last in BINS:
            where = (model.ell >= first) & (model.ell <= last)
            modes = 2 * model.ell[where] + 1.0
            term = args.r * model.c_gw_r1[where]
            per_seed = (added[:, where] * modes).sum(axis=1) / np.sum(modes * term)
            error = per_seed.std(ddof=1) / np.sqrt(per_seed.size)
            used = (ell_used >= first) & (ell_used <= last)
            share = information[used].sum() / information.sum()
            print(f"  {first:3d}-{last:3d}  {per_seed.mean():6.3f} +- {error:.3f}  {share:6.3f}")
    print()


if __name__ == "__main__":
    main()
