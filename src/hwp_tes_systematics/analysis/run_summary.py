"""What a run is and where its answer stands, for requirement.json and the report.

The settings that tell runs apart (:func:`run_settings`), the run in one sentence
(:func:`describe_run`), its answer beside the shipped one-year answer when the two are
one analysis (:func:`one_year_comparison`), and the answer with its checks in a few rows
(:func:`answer_table`, the report's first page).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd

from .. import config as cfg


def run_settings(config: dict) -> dict:
    """The settings a reader of requirement.json needs to tell runs apart."""
    simulation = config["simulation"]
    return {
        "channels": len(cfg.selected_channels(config)),
        "seeds": simulation["seeds"],
        "chunk_stride": simulation["chunk_stride"],
        "days_simulated": days_simulated(config),
        "noise_scale": simulation["noise_scale"],
        "map_maker": config["maps"]["map_maker"],
        "analysis_nside": cfg.analysis_nside(config),
        "baseline_length_s": config["maps"]["baseline_length_s"],
        "g1_per": config["requirement"]["g1_per"],
        "pairs_per_channel": config["instrument"]["pairs_per_channel"],
        "emulated_pairs_per_channel": config["instrument"]["emulated_pairs_per_channel"],
        "detector_positions": config["instrument"]["detector_positions"],
        "likelihood_model": config["likelihood"]["model"],
        "notch_width_divisor": config["notch"]["width_divisor"],
        "removed_hwp_harmonics": config["maps"]["removed_hwp_harmonics"],
        "hwpss_a2_over_delta_p": config["optics"]["hwpss_a2_over_delta_p"],
        "duration_days": simulation["duration_days"],
        "nside": config["maps"]["nside"],
        "cmb_r": simulation["cmb_r"],
    }


# run_settings that make two runs one analysis of the same instrument: a run that differs
# from the shipped one-year answer in none of them is put beside it (its days may differ);
# a file made before a key was logged holds its value then (OLDER_SETTINGS)
SAME_ANALYSIS_KEYS = (
    "baseline_length_s", "g1_per", "pairs_per_channel", "emulated_pairs_per_channel",
    "detector_positions",
    "likelihood_model", "notch_width_divisor", "removed_hwp_harmonics",
    "hwpss_a2_over_delta_p", "nside", "cmb_r", "channels", "map_maker", "analysis_nside",
)  # fmt: skip
OLDER_SETTINGS = {
    "channels": 22, "map_maker": "binned", "chunk_stride": 1, "emulated_pairs_per_channel": None,
}  # fmt: skip


def days_simulated(config: dict) -> float:
    """Days of TOD simulated: the chunks of the duration, every ``chunk_stride``-th."""
    simulation = config["simulation"]
    duration_s, chunk_s = simulation["duration_days"] * 86400.0, simulation["chunk_duration_s"]
    starts = np.arange(math.ceil(duration_s / chunk_s))[:: simulation["chunk_stride"]] * chunk_s
    return float(np.minimum(chunk_s, duration_s - starts).sum() / 86400.0)


def describe_run(config: dict) -> str:
    """What the run is, in one sentence: its observation, channels, seeds and maps."""
    settings = run_settings(config)
    duration, stride = config["simulation"]["duration_days"], settings["chunk_stride"]
    chunk_h = config["simulation"]["chunk_duration_s"] / 3600.0
    chunk = "day" if chunk_h == 24.0 else f"{chunk_h:g}-hour chunk"
    observed = (
        f"{duration:g} days"
        if stride == 1
        else f"{duration:g} days sampled one {chunk} in {stride} ({settings['days_simulated']:g}"
        " days simulated, the noise scaled to the whole duration's white-noise depth; the "
        "template averages over the days simulated only)"
    )
    baselines = settings["baseline_length_s"]
    offsets = "no offsets removed" if baselines is None else f"{baselines:g} s offsets removed"
    pairs = f"{settings['pairs_per_channel']} detector pair(s) each"
    emulated = settings["emulated_pairs_per_channel"]
    if emulated is not None:
        count = "every pair of the channel" if emulated == "all" else f"{emulated} pairs"
        pairs += f", their seeds emulating {count} (noise and g1 scaled)"
    return (
        f"{observed}; {settings['channels']} channels, {pairs}; {settings['seeds']} seeds; "
        f"{settings['map_maker']} maps at nside {settings['nside']} with {offsets}; analysed "
        f"on the nside-{settings['analysis_nside']} mask; likelihood model "
        f"{settings['likelihood_model']}"
    )


def one_year_comparison(headline: dict, settings: dict) -> dict:
    """This run's answer beside the shipped one-year answer (:func:`config.
    one_year_requirement_path`): the ratio when the two are one analysis
    (SAME_ANALYSIS_KEYS), else the settings that differ."""
    path = cfg.one_year_requirement_path()
    shipped = json.loads(path.read_text())
    theirs = {
        **OLDER_SETTINGS,
        "analysis_nside": shipped["settings"]["nside"],
        "seeds": shipped["n_seeds"],
    }
    theirs.update(shipped["settings"])
    differing = [key for key in SAME_ANALYSIS_KEYS if theirs[key] != settings[key]]
    answer = shipped["headline"]["requirement_sigma_g1_per_k"]
    comparison = {
        "source": f"the shipped one-year answer ({cfg.ONE_YEAR_REQUIREMENT_SOURCE})",
        "requirement_sigma_g1_per_k": answer,
        "error_per_k": shipped["headline"]["error_per_k"],
        "fisher_peak_shift_requirement_sigma_g1_per_k": shipped["headline"][
            "fisher_peak_shift_requirement_sigma_g1_per_k"
        ],
        "same_analysis": not differing,
        "differing_settings": differing,
    }
    if differing:
        comparison["note"] = (
            f"the one-year answer ({answer:.3g} 1/K) is of another analysis: "
            f"{', '.join(differing)} differ"
        )
        return comparison
    ratio = answer / headline["requirement_sigma_g1_per_k"]
    comparison["one_year_over_this_run"] = ratio
    if settings["chunk_stride"] == theirs["chunk_stride"] and settings["seeds"] == theirs["seeds"]:
        comparison["note"] = f"the one-year answer's configuration: ratio {ratio:.3f}"
    else:
        comparison["note"] = (
            f"the one-year answer of the same analysis is {answer:.3g} 1/K, {ratio:.2f} times "
            "this run's (a sampled year averages the template over fewer days: "
            "docs/results/year_sampled.md)"
        )
    return comparison


def answer_table(output: dict) -> pd.DataFrame:
    """The run's answer in a few rows (quantity, value): the requirement by the headline's
    convention and by the Fisher peak shift, the checks it rests on, what the run is and
    where it stands beside the one-year answer: the report's first page."""
    headline = output["headline"]
    beside = headline["one_year_answer"]

    def verdict(value) -> str:
        return "not run" if value is None else ("passes" if value else "FAILS")

    rows = [
        ("sigma_g1 requirement, 68 % point [1/K]", f"{headline['requirement_sigma_g1_per_k']:.3g}"),
        ("its error (bootstrap over seeds) [1/K]", f"{headline['error_per_k']:.2g}"),
        ("the seeds' scatter [1/K]", f"{headline['std_over_seeds_per_k']:.2g}"),
        (
            "sigma_g1 requirement, Fisher peak shift [1/K]",
            f"{headline['fisher_peak_shift_requirement_sigma_g1_per_k']:.3g}",
        ),
        ("delta r budget", f"{output['delta_r_budget']:g}"),
        ("sigma_r (Fisher, r = 0)", f"{headline['sigma_r_fisher']:.3g}"),
        ("likelihood model", headline["model"]),
        ("model check, all seeds", verdict(headline["consistent"])),
        ("model check, held-out seeds", verdict(headline["consistent_held_out"])),
        ("r read back on held-out seeds", verdict(headline["r_recovered_consistent"])),
        ("verdict", headline["note"]),
        ("this run", headline["run"]),
        ("beside the one-year answer", beside["note"]),
        ("Micheli et al. 2024", "sigma_g1 < 2e-3 1/K (one pair per channel, their model)"),
    ]
    return pd.DataFrame(rows, columns=["quantity", "value"])
