"""How long must a detector observe for its own data to calibrate g1 below the requirement?

    python benchmarks/calibration_vs_length.py --channels M1-140 H1-195 H3-402 \\
        --hours 1 2 4 --predict 8 --seeds 4 --json out.json --figure out.png

Per channel and recording length: recordings of one detector pair with g1 drawn per
detector from N(0, --g1-spread) and the nominal errors of a real recording
(:func:`hwp_tes_systematics.diagnose.testbed.nominal_errors`, drawn per recording), each
diagnosed (never told the effect). The diagnosis's g1 per detector (fitted when it selects
the nonlinearity, fitted beside the effects it found when not) is the calibration a TOD
correction would use (``instrument.nonlinearity.linearize``); its error g1_hat - g1 is
what the correction leaves. Printed per (channel, hours): the rms error over detectors and
recordings, its mean (a shared sign does not average down over a focal plane), the
slope of g1_hat on g1, the median formal sigma, and how often the nonlinearity was
selected. ``--a4-k`` adds a 4 f_HWP HWPSS harmonic of that amplitude and a random phase
per detector, which the model of the nonlinearity must not take for its 4 f_HWP line.

The rms error is fitted as ``A (T / 1 h)^a`` on the ``--hours`` lengths per channel and
predicts the ``--predict`` lengths, which are then run and compared (a scaling law tested
on a length it was not fitted to). Against a workflow's requirement (``--requirement``,
default the shipped one-year result) at the same HWPSS amplitude (``systematic_only`` ->
``by_a2_scale``: the leak scales with A_2, so a smaller HWPSS has a looser requirement):
sigma_cal / sigma_req (Fisher; at the nominal A_2 also the 68 % point), the residual
bias delta r = budget (sigma_cal / sigma_req)^2 (the systematic's own power is exactly
quadratic in sigma_g1) if every detector of the focal plane were calibrated as this
channel's are, beside the bias of no correction (the drawn g1's own spread), and the
shortest length run from which sigma_cal stays below sigma_req (no extrapolation).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import tempfile
import time
from importlib import resources
from pathlib import Path

import numpy as np

from hwp_tes_systematics.diagnose import diagnose, testbed

MASTER_SEED = 20261130


def diagnosed_g1(
    channel: str, hours: float, seed: int, options: argparse.Namespace, a2_scale: float, folder
) -> list:
    """[(g1 injected, g1 diagnosed, formal sigma, selected, covered)] per detector of one
    recording, its HWPSS amplitude A_2 the channel's nominal one times ``a2_scale``;
    covered: what the diagnosis says of g1 holds the injected one (selected: within 3
    times its uncertainty, a second solution included; else below its bound)."""
    key = [sum(map(ord, channel)), round(hours * 600), round(a2_scale * 1000), seed]
    rng = np.random.default_rng([MASTER_SEED, *key, round(options.a4_k * 1e9)])
    a2_k = testbed.nominal(channel)["a2_k"] * a2_scale
    g1 = rng.normal(options.g1_mean, options.g1_spread, 2)
    errors = testbed.nominal_errors(rng)
    effects = [("tes_nonlinearity", {"g1": g1})]
    if options.a4_k > 0:
        phase = rng.uniform(0.0, 2 * np.pi, 2)
        a4 = {"c4": options.a4_k * np.cos(phase), "s4": options.a4_k * np.sin(phase)}
        effects.append(("hwpss_harmonics", a4))
    recording, _ = testbed.recorded_with_errors(
        folder,
        effects,
        int(rng.integers(1, 2**31)),
        errors,
        hours=hours,
        name=f"{channel}_{hours:g}h_{seed}.h5",
        channel=channel,
        a2_k=a2_k,
    )
    result = diagnose(recording, testbed.supplied_sky(errors), a2_k, figures=False)
    check = result["requirement_check"]
    selected = check["detected"]
    return [
        (float(g1[k]), d["g1_per_k"], d["sigma_per_k"], selected, covers(d, float(g1[k])))
        for k, d in enumerate(check["detectors"])
    ]


def covers(detector: dict, g1: float) -> bool:
    """Does a detector's entry of the requirement check hold the injected ``g1``?"""
    if "bound_per_k" in detector:
        return abs(g1) < detector["bound_per_k"]
    return abs(detector["g1_per_k"] - g1) < 3 * detector["uncertainty_per_k"]


def summarise(rows: list) -> dict:
    true = np.array([row[0] for row in rows])
    errors = np.array([hat - g1 for g1, hat, *_ in rows])
    return {
        "rms_error_per_k": float(np.sqrt(np.mean(errors**2))),
        "mean_error_per_k": float(np.mean(errors)),
        "rms_g1_per_k": float(np.sqrt(np.mean(true**2))),  # what no correction leaves
        "slope": float(np.polyfit(true, true + errors, 1)[0]),  # g1_hat on g1
        "median_sigma_per_k": float(np.median([row[2] for row in rows])),
        "selected_fraction": float(np.mean([row[3] for row in rows])),
        "covered_fraction": float(np.mean([row[4] for row in rows])),
        "n_detectors": len(rows),
        "detectors": [list(row) for row in rows],
    }


def shortest_below(per_length: dict, sigma_req: float) -> float | None:
    """The shortest length run whose rms calibration error is below ``sigma_req`` and
    stays below it at every longer length run (None: none)."""
    lengths = sorted(per_length)
    below = [per_length[h]["rms_error_per_k"] < sigma_req for h in lengths]
    for i, hours in enumerate(lengths):
        if all(below[i:]):
            return hours
    return None


def power_law(hours, values) -> tuple[float, float]:
    """(A, a) of values = A (T / 1 h)^a, least squares in log-log."""
    slope, intercept = np.polyfit(np.log(hours), np.log(values), 1)
    return math.exp(intercept), slope


def requirement_at(data: dict, a2_scale: float) -> dict:
    """{fisher, 68} sigma_req [1/K] at this HWPSS scale: the headline's at the nominal A_2,
    else the Fisher one of ``systematic_only.by_a2_scale`` (the 68 % point is not made per
    scale); an error naming the scales the file has when it lacks this one."""
    headline = data["headline"]
    if a2_scale == 1.0:
        return {
            "Fisher": headline["fisher_peak_shift_requirement_sigma_g1_per_k"],
            "68 %": headline["requirement_sigma_g1_per_k"],
        }
    scales = data["systematic_only"].get("by_a2_scale", [])
    for entry in scales:
        if math.isclose(entry["a2_scale"], a2_scale):
            return {"Fisher": entry["requirement_sigma_g1_per_k"]}
    have = [entry["a2_scale"] for entry in scales]
    raise SystemExit(f"--a2-scales {a2_scale:g}: the requirement file has A_2 scales {have}")


def length_law(label: str, per_length: dict, fit_hours, predict_hours) -> dict:
    """The rms error as A (T / 1 h)^a on ``fit_hours``, and its predictions (printed)."""
    if len(fit_hours) < 2:
        return {}
    amplitude, slope = power_law(fit_hours, [per_length[h]["rms_error_per_k"] for h in fit_hours])
    law = {"amplitude_1h_per_k": amplitude, "exponent": slope, "predictions": {}}
    for hours in predict_hours:
        predicted, measured = amplitude * hours**slope, per_length[hours]["rms_error_per_k"]
        law["predictions"][hours] = {"predicted": predicted, "measured": measured}
        print(
            f"{label}: rms error = {amplitude:.3g} (T / 1 h)^{slope:.2f} K^-1 on "
            f"{', '.join(f'{h:g}' for h in fit_hours)} h; at {hours:g} h it predicts "
            f"{predicted:.3g}, measured {measured:.3g} (ratio {measured / predicted:.2f})"
        )
    return law


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Example: python benchmarks/calibration_vs_length.py --channels M1-140 "
        "--hours 1 2 --predict 4 --seeds 2",
    )
    parser.add_argument("--channels", nargs="+", default=["M1-140", "H1-195", "H3-402"])
    parser.add_argument("--hours", nargs="+", type=float, default=[1.0, 2.0, 4.0])
    parser.add_argument("--predict", nargs="*", type=float, default=[8.0])
    parser.add_argument("--seeds", type=int, default=4, help="recordings per length")
    parser.add_argument("--g1-spread", type=float, default=5e-3, help="sigma of g1 drawn [1/K]")
    parser.add_argument("--g1-mean", type=float, default=0.0, help="mean of g1 drawn [1/K]")
    parser.add_argument(
        "--a2-scales", nargs="+", type=float, default=[1.0], help="A_2 / the channel's nominal"
    )
    parser.add_argument(
        "--a4-k", type=float, default=0.0, help="a 4 f_HWP HWPSS harmonic injected too [K]"
    )
    parser.add_argument("--requirement", type=Path, help="a run's requirement.json")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--figure", type=Path)
    arguments = parser.parse_args()
    if arguments.requirement:
        source = str(arguments.requirement)
        data = json.loads(arguments.requirement.read_text())
    else:
        source = "the shipped one-year result (docs/one_year/recovered_power/requirement.json)"
        shipped = resources.files("hwp_tes_systematics") / "data" / "one_year_requirement.json"
        data = json.loads(shipped.read_text())
    budget = data["delta_r_budget"]
    print(
        f"requirement: {source}; delta r budget {budget:g}; g1 ~ N({arguments.g1_mean:g}, "
        f"{arguments.g1_spread:g}) K^-1; 4 f_HWP harmonic injected: {arguments.a4_k:g} K"
    )
    print(
        "| channel | hours | rms(g1_hat - g1) [1/K] | mean | slope | median sigma [1/K] "
        "| selected | sigma_cal / sigma_req (Fisher; 68 %) | delta r (Fisher): corrected "
        "/ uncorrected | covered | wall [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    options = {k: str(v) if isinstance(v, Path) else v for k, v in vars(arguments).items()}
    out = {"requirement": source, "budget": budget, "options": options}
    out["channels"] = {}
    with tempfile.TemporaryDirectory() as folder:
        for channel, a2_scale in itertools.product(arguments.channels, arguments.a2_scales):
            label = channel if a2_scale == 1.0 else f"{channel}, A_2 x {a2_scale:g}"
            sigma_req = requirement_at(data, a2_scale)
            per_length = {}
            for hours in sorted({*arguments.hours, *arguments.predict}):
                started = time.perf_counter()
                rows = []
                for seed in range(arguments.seeds):
                    rows += diagnosed_g1(channel, hours, seed, arguments, a2_scale, Path(folder))
                    for path in Path(folder).glob("*.h5"):
                        path.unlink()
                row = summarise(rows) | {"wall_s": time.perf_counter() - started}
                sigma_cal = row["rms_error_per_k"]
                row["sigma_req_per_k"] = sigma_req
                row["residual_delta_r_fisher"] = budget * (sigma_cal / sigma_req["Fisher"]) ** 2
                row["uncorrected_delta_r_fisher"] = (
                    budget * (row["rms_g1_per_k"] / sigma_req["Fisher"]) ** 2
                )
                per_length[hours] = row
                ratios = "; ".join(f"{sigma_cal / s:.3g}" for s in sigma_req.values())
                print(
                    f"| {label} | {hours:g} | {sigma_cal:.3g} | {row['mean_error_per_k']:.2g} "
                    f"| {row['slope']:.3f} | {row['median_sigma_per_k']:.3g} "
                    f"| {row['selected_fraction']:.2f} | {ratios} "
                    f"| {row['residual_delta_r_fisher']:.3g} / "
                    f"{row['uncorrected_delta_r_fisher']:.3g} | {row['covered_fraction']:.2f} "
                    f"| {row['wall_s']:.0f} |",
                    flush=True,
                )
            law = length_law(label, per_length, arguments.hours, arguments.predict)
            for convention, limit in sigma_req.items():
                law[f"first_length_below_{convention}_h"] = first = shortest_below(
                    per_length, limit
                )
                if first is None:
                    text = "at none of the lengths run"
                elif first == min(per_length):
                    text = f"already at the shortest length run, {first:g} h"
                else:
                    text = f"from {first:g} h (the shortest length run that does)"
                print(f"{label}: sigma_cal is below the {convention} requirement {text}")
            out["channels"][label] = {"per_length": per_length, "law": law, "a2_scale": a2_scale}
    if arguments.json:
        arguments.json.write_text(json.dumps(out, indent=2) + "\n")
    if arguments.figure:
        draw(out, arguments.figure)


def draw(out: dict, path: Path) -> None:
    from hwp_tes_systematics.figures import save_figure, subplots

    fig, ax = subplots(figsize=(7.5, 4.2))
    for channel, entry in out["channels"].items():
        hours = sorted(entry["per_length"], key=float)
        values = [entry["per_length"][h]["residual_delta_r_fisher"] for h in hours]
        ax.plot([float(h) for h in hours], values, "o-", label=channel)
    ax.axhline(out["budget"], color="k", ls="--", lw=1, label="budget")
    lengths = sorted({float(h) for entry in out["channels"].values() for h in entry["per_length"]})
    ax.set_xscale("log")
    ax.set_xticks(lengths, [f"{h:g}" for h in lengths])
    ax.minorticks_off()
    ax.set_yscale("log")
    ax.set_xlabel("recording length [h]")
    ax.set_ylabel(r"residual $\delta r$ after the correction (Fisher)")
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    save_figure(fig, path)


if __name__ == "__main__":
    main()
