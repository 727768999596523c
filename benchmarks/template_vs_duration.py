"""How the nonlinearity template averages down with the observing time and the pixel
size, with and without per-detector baselines, for the binned map-maker and for HWP
demodulation + low-pass (issue 13 item 3: which terms of d^2 reach BB, and through
which map-maker).

    python benchmarks/template_vs_duration.py --channels M1-140 H3-402 --days 1 7 30 \
        --nsides 64 512 --rate 19 --json docs/one_year/template_vs_duration.json \
        --figure docs/one_year/template_vs_duration.png
    python benchmarks/template_vs_duration.py --days 1 --hwp-rate-factors 1 1.00064
    python benchmarks/template_vs_duration.py --days 0 --merge a.json b.json --json all.json \
        --figure all.png       # only merge runs made in parallel and draw them

``--hwp-rate-factors`` scales the HWP rotation rate (and the notch with it): at the
nominal 39 rpm (MFT) the HWP turns exactly 780 times per 20-minute spin period (61 rpm,
HFT: 1220), so the leakage of successive spins can add coherently; a factor of
1.00064 (half a turn more per spin) breaks the commensurability.

For each (channel, duration, nside, rate factor), one pair is simulated through the job
path (sky, dipole, noise at the default config's noise_scale, the channel's A_2 from
the default optics), once with 60 s baselines and once on the paper-literal path; the
same filtered TODs (2f removal + notch) are binned by the binned solve and by
demodulation + low-pass (:mod:`demodulation`), and the template terms s^2, s h, h^2
of detector 0 are summarised. Printed per term: the Q/U rms per unit g1 over the
observed pixels [K_CMB K] and the BB pseudo-spectrum (the binned solve's observed
pixels, / f_sky) averaged over ell 2-12, 13-40, 41-128 [K_CMB^2 K^2], and the
correlation of the two detectors' total templates. ``--json`` keeps the rows,
``--figure`` draws the total template's BB at ell 2-12 and 41-128 against the duration
(one panel per channel and nside). Each point runs in this process, one thread; a year
of a pair takes ~15-25 min at 31 Hz.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import healpy as hp
import numpy as np

from hwp_tes_systematics.config import default_config_path, load_config
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.io import atomic_path
from hwp_tes_systematics.simulation.channel_inputs import channel_a2_k_cmb, channel_sky
from hwp_tes_systematics.simulation.demodulation import DemodulatedEquations
from hwp_tes_systematics.simulation.mapmaking import solve_maps
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import (
    TEMPLATE_TERMS,
    PairMapSettings,
    accumulate,
    split_solved_maps,
)

ELL_BINS = ((2, 13), (13, 41), (41, 129))


def template_summary(terms, templates, good, nside):
    """Rows of (term, Q/U rms, BB per ell bin) for detector 0, and the detectors' correlation."""
    fsky = good.mean()
    rows = []
    labeled = [(name, terms[index, 0]) for index, name in enumerate(TEMPLATE_TERMS)]
    for name, maps in [*labeled, ("total", templates[0])]:
        masked = np.where(good, maps, 0.0)
        rms = float(np.sqrt(np.mean(maps[1:, good] ** 2)))
        bb = hp.anafast(masked, lmax=3 * nside - 1)[2] / fsky
        rows.append((name, rms, [float(bb[lo:hi].mean()) for lo, hi in ELL_BINS]))
    correlation = float(
        np.corrcoef(templates[0][1:, good].ravel(), templates[1][1:, good].ravel())[0, 1]
    )
    return rows, correlation


def one_point(config, channel_name, days, nside, baseline_length_s, hwp_rate_factor=1.0, rate=None):
    """{map-maker: (summary rows, detector correlation)} and the observed fraction of one
    simulated pair, binned and demodulated from the same filtered TODs."""
    channel = load_channel(channel_name)
    channel = dataclasses.replace(channel, hwp_rpm=channel.hwp_rpm * hwp_rate_factor)
    plan = MissionPlan(
        config["simulation"]["mission_start_tdb"],
        days * 86400.0,
        86400.0,
        rate or channel.sampling_rate_hz,
    )
    a2_k = channel_a2_k_cmb(config, channel_name)
    settings = PairMapSettings.from_config(
        config, channel, 0, a2_k, plan=plan, nside=nside, baseline_length_s=baseline_length_s
    )
    simulator = PairSimulator(channel, plan, nside)
    simulator.hwp_rad_per_s = channel.hwp_frequency_hz * 2 * np.pi  # the scaled rate
    sky = channel_sky({**config, "maps": {**config["maps"], "nside": nside}}, channel, 0)["total"]
    demodulated = DemodulatedEquations(nside, 1 + len(TEMPLATE_TERMS) * simulator.n_detectors)
    maps, _, good = solve_maps(accumulate(simulator, settings, sky, demodulated=demodulated), 100.0)
    summaries = {}
    for map_maker, solved_maps in (("binned", maps), ("demodulated", demodulated.solve())):
        solved = split_solved_maps(solved_maps, simulator.n_detectors, a2_k)
        summaries[map_maker] = template_summary(
            solved["template_terms"], solved["templates"], good, nside
        )
    return summaries, good


def plot_total_bb(rows: list[dict], path: Path) -> None:
    """Total template BB (ell 2-12 solid, 41-128 dashed) against the duration, one panel
    per (channel, nside), a colour per (map-maker, baselines); the demodulated map with
    baselines is drawn in open markers, as it lies on the one without."""
    from hwp_tes_systematics.figures import save_figure, subplots

    totals = [row for row in rows if row["term"] == "total" and row["hwp_rate_factor"] == 1.0]
    panels = sorted({(row["channel"], row["nside"]) for row in totals})
    fig, axes = subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6), squeeze=False)
    styles = {
        ("binned", "60.0"): "C0",
        ("binned", "none"): "C1",
        ("demodulated", "60.0"): "C2",
        ("demodulated", "none"): "C3",
    }
    for axis, (channel, nside) in zip(axes[0], panels, strict=True):
        for (map_maker, baselines), color in styles.items():
            points = sorted(
                (row["days"], row["bb"])
                for row in totals
                if (row["channel"], row["nside"], row["map_maker"], row["baselines"])
                == (channel, nside, map_maker, baselines)
            )
            if not points:
                continue
            days = [day for day, _ in points]
            label = f"{map_maker}, baselines {baselines}"
            lies_on_another = (map_maker, baselines) == ("demodulated", "60.0")
            open_markers = {"markerfacecolor": "none", "markersize": 9} if lies_on_another else {}
            ell_low = [bb[0] for _, bb in points]
            ell_high = [bb[2] for _, bb in points]
            axis.loglog(days, ell_low, "o-", color=color, label=label, **open_markers)
            axis.loglog(days, ell_high, "s--", color=color, alpha=0.6, **open_markers)
        axis.set_title(f"{channel}, nside {nside}")
        axis.set_xlabel("observing time [days]")
    axes[0][0].set_ylabel("template BB per unit g1$^2$ [K$^2$ K$^2$]\n(o: ell 2-12, s: 41-128)")
    axes[0][0].legend(fontsize=7)
    save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", nargs="+", default=["M1-140"])
    parser.add_argument("--days", type=float, nargs="+", default=[1.0])
    parser.add_argument("--nsides", type=int, nargs="+", default=[64])
    parser.add_argument("--hwp-rate-factors", type=float, nargs="+", default=[1.0])
    parser.add_argument("--rate", type=float, default=None, help="sampling rate [Hz] (IMO's)")
    parser.add_argument("--json", type=Path, help="write the rows here (appends to a file)")
    parser.add_argument("--figure", type=Path, help="draw the rows of --json here")
    parser.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=[],
        help="JSON files of earlier runs (e.g. one per channel, run in parallel) to add to the "
        "rows; with --days 0 nothing new is simulated and only --json / --figure are written",
    )
    arguments = parser.parse_args()
    config = load_config(default_config_path())
    rows = (
        json.loads(arguments.json.read_text()) if arguments.json and arguments.json.exists() else []
    )
    for path in arguments.merge:
        rows += json.loads(path.read_text())
    if arguments.json and arguments.merge:
        with atomic_path(arguments.json) as temporary:
            Path(temporary).write_text(json.dumps(rows, indent=1))
    print(
        "| channel | days | nside | HWP rate x | baselines | map-maker | term | Q/U rms per unit "
        "g1 [K K] | BB ell 2-12 | ell 13-40 | ell 41-128 [K^2 K^2] | observed | detector "
        "correlation | wall [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    points = [
        (channel, days, nside, factor, baselines)
        for channel in arguments.channels
        for days in arguments.days
        for nside in arguments.nsides
        for factor in arguments.hwp_rate_factors
        for baselines in (60.0, None)
        if days > 0
    ]
    for channel, days, nside, factor, baselines in points:
        started = time.perf_counter()
        summaries, good = one_point(config, channel, days, nside, baselines, factor, arguments.rate)
        wall = time.perf_counter() - started
        for map_maker, (summary_rows, correlation) in summaries.items():
            for name, rms, bb in summary_rows:
                row = {
                    "channel": channel,
                    "days": days,
                    "nside": nside,
                    "hwp_rate_factor": factor,
                    "baselines": str(baselines or "none"),
                    "map_maker": map_maker,
                    "term": name,
                    "qu_rms_k_k": rms,
                    "bb": bb,
                    "observed_fraction": float(good.mean()),
                    "detector_correlation": correlation,
                    "wall_s": wall,
                    "rate_hz": arguments.rate,
                }
                rows.append(row)
                print(
                    f"| {channel} | {days:g} | {nside} | {factor:g} | {row['baselines']} | "
                    f"{map_maker} | {name} | {rms:.3g} | {bb[0]:.2g} | {bb[1]:.2g} | "
                    f"{bb[2]:.2g} | {good.mean():.0%} | {correlation:+.4f} | {wall:.0f} |",
                    flush=True,
                )
        if arguments.json:
            arguments.json.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(arguments.json) as temporary:
                Path(temporary).write_text(json.dumps(rows, indent=1))
    if arguments.figure:
        plot_total_bb(rows, arguments.figure)
        print(f"figure: {arguments.figure}")


if __name__ == "__main__":
    main()
