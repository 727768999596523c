"""The requirement against the number of detector pairs per channel, from runs at several N.

    python benchmarks/requirement_vs_pairs.py 1=n1/results/requirement.json \\
        2=n2/results/requirement.json 4=n4/... 8=n8/... --fit 1 2 4 --figure out.png

Reads each run's ``requirement.json`` (``instrument.pairs_per_channel: N``) and prints, per
N: the random population's requirement on sigma_g1 (the paper's convention, the mean over
seeds of the 68 %-point shift, with its bootstrap error; and the Fisher peak shift of the
systematic's own power through the HILC weights, delta r = k sigma^2), the common
offset's requirement on |mu_g1| (with its linear term and from its own power alone) with
``k_mu / k_sigma``, and sigma_r. Each is fitted as a power law ``A N^a`` on the ``--fit``
runs (least squares in log-log, weighted by the errors where the run gives them), and the
fit predicts the other runs (the prediction, the run's value and their ratio) and the N of
``--predict`` not run yet.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

# (label, reader of requirement.json -> (value, error or None))
QUANTITIES = {
    "random sigma_g1, 68 % point [1/K]": lambda d: (
        d["headline"]["requirement_sigma_g1_per_k"],
        d["headline"].get("error_per_k"),
    ),
    "random sigma_g1, Fisher [1/K]": lambda d: (
        d["headline"]["fisher_peak_shift_requirement_sigma_g1_per_k"],
        d["headline"].get("fisher_peak_shift_error_per_k"),
    ),
    "common |mu_g1|, with b [1/K]": lambda d: (d["common_offset"]["requirement_mu_per_k"], None),
    "common |mu_g1|, own power [1/K]": lambda d: (
        d["common_offset"]["requirement_mu_quadratic_only_per_k"],
        None,
    ),
    "k_mu / k_sigma": lambda d: (d["common_offset"]["k_over_k_random"], None),
    "sigma_r (Fisher)": lambda d: (d["sigma_r_fisher"], None),
}


def power_law(n_pairs, values, errors=None) -> tuple[float, float, float]:
    """(A, a, sigma_a) of values = A N^a, least squares in log-log (weights 1 / relative error)."""
    x, y = np.log(n_pairs), np.log(values)
    weights = None
    if errors is not None and all(e is not None and e > 0 for e in errors):
        weights = np.asarray(values) / np.asarray(errors)
    coefficients, covariance = np.polyfit(x, y, 1, w=weights, cov="unscaled")
    if weights is None and len(x) > 2:  # the scatter about the line as the error
        residual = y - np.polyval(coefficients, x)
        covariance = covariance * residual.var(ddof=2) * len(x) / (len(x) - 2)
    slope_sigma = math.sqrt(covariance[0, 0]) if len(x) > 2 or weights is not None else math.nan
    return math.exp(coefficients[1]), coefficients[0], slope_sigma


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="N=path/to/requirement.json")
    parser.add_argument("--fit", nargs="+", type=int, help="the N the power laws are fitted on")
    parser.add_argument("--predict", nargs="*", type=int, default=[], help="N not run: predicted")
    parser.add_argument("--figure", type=Path, help="the requirement against N (PNG)")
    args = parser.parse_args()
    runs = {}
    for item in args.runs:
        n, _, path = item.partition("=")
        if not path:
            parser.error(f"{item!r}: expected N=path/to/requirement.json")
        data = json.loads(Path(path).read_text())
        if data["settings"].get("pairs_per_channel") != int(n):
            parser.error(
                f"{path}: pairs_per_channel is {data['settings'].get('pairs_per_channel')}, not {n}"
            )
        runs[int(n)] = data
    n_all = sorted(runs)
    fit_n = sorted(args.fit or n_all)
    print(f"runs: N = {n_all}; power laws fitted on N = {fit_n}")
    table = {}
    for label, read in QUANTITIES.items():
        values = {n: read(runs[n]) for n in n_all}
        table[label] = values
        text = "  ".join(
            f"N={n}: {v:.3g}" + (f" +- {e:.2g}" if e else "") for n, (v, e) in values.items()
        )
        print(f"{label:36s} {text}")
        fitted = [n for n in fit_n if n in values]
        if len(fitted) < 2:
            continue
        amplitude, slope, slope_sigma = power_law(
            fitted, [values[n][0] for n in fitted], [values[n][1] for n in fitted]
        )
        line = f"{'':36s} fit on N = {fitted}: A N^a, a = {slope:+.3f} +- {slope_sigma:.3f}"
        for n in n_all:
            if n in fitted:
                continue
            predicted = amplitude * n**slope
            value, error = values[n]
            line += (
                f"; predicts N={n}: {predicted:.3g} (run {value:.3g}, ratio {value / predicted:.3f}"
            )
            line += f", {(value - predicted) / error:+.1f} sigma)" if error else ")"
        for n in args.predict:
            line += f"; predicts N={n} (not run): {amplitude * n**slope:.3g}"
        print(line)
    if args.figure:
        from hwp_tes_systematics.figures import save_figure, subplots

        fig, ax = subplots(figsize=(6.4, 4.4))
        n_array = np.array(n_all, dtype=float)
        for label, marker in (
            ("random sigma_g1, 68 % point [1/K]", "o"),
            ("random sigma_g1, Fisher [1/K]", "s"),
            ("common |mu_g1|, with b [1/K]", "v"),
            ("common |mu_g1|, own power [1/K]", "D"),
        ):
            values = np.array([table[label][n][0] for n in n_all])
            errors = np.array([table[label][n][1] or 0.0 for n in n_all])
            ax.errorbar(n_array, values, errors, marker=marker, capsize=3, label=label[:-6])
        reference = table["random sigma_g1, Fisher [1/K]"][n_all[0]][0]
        ax.plot(n_array, reference * np.sqrt(n_array / n_all[0]), "k:", label="sqrt(N) from N = 1")
        ax.set(
            xscale="log",
            yscale="log",
            xlabel="detector pairs per channel N",
            ylabel="requirement [1/K]",
            xticks=n_all,
            xticklabels=[str(n) for n in n_all],
        )
        ax.legend(fontsize=7, loc="best")
        save_figure(fig, args.figure)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
