"""The map-domain path against the full-TOD path, on two runs of the same configuration
that differ only in ``simulation.realizations`` (the same seeds: the same CMB draws,
different noise draws).

    snakemake --cores 2 results/requirement.json --configfile over.yaml          # in TOD/
    snakemake --cores 2 results/requirement.json --configfile over.yaml md.yaml  # in MD/
    python benchmarks/map_domain_validation.py --tod TOD --map-domain MD \
        --configfile config/config.yaml over.yaml md.yaml

(md.yaml: ``simulation: {realizations: map_domain}``; ``--configfile``: the map-domain
run's configuration, whose seeds' maps are made again from its fixed passes, as its
map_domain_alms jobs made them in memory.) Printed, as Markdown:

1. per channel, the Q/U rms over the observed pixels of the noise (nosys minus the CMB
   and foreground references, averaged over seeds) and of the templates of detector 0;
2. the nosys residual BB spectrum (HILC residual, its noise part) per multipole band,
   mean over seeds;
3. the systematic-only Fisher bias k = delta r / sigma_g1^2 and the paper estimator's
   delta r per sigma_g1, mean over seeds with its standard error, for both paths, their
   ratio and their difference in units of the combined error; sigma_r.

The paths share each seed's CMB draw, not its noise draw: per seed they differ by noise,
so they are compared through the seed means (the paper's estimator at small sigma_g1
scatters by 10x and more between seeds: many seeds are needed).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import healpy as hp
import numpy as np
import pandas as pd

from hwp_tes_systematics.config import analysis_variant, load_config
from hwp_tes_systematics.simulation.map_domain import ChannelSeeds
from hwp_tes_systematics.simulation.maps_file import read_channel_maps

ELL_BANDS = ((2, 12), (12, 40), (40, 80), (80, 129))


def qu_rms(maps: np.ndarray, seen: np.ndarray) -> float:
    return float(np.sqrt(np.mean(maps[1:, seen] ** 2)))


def seed_maps(folder: Path, config: dict | None):
    """Each seed's maps of a channel: its maps files (TOD path), or made from its fixed
    pass (map-domain path, ``config`` given)."""
    if config is None:
        return [read_channel_maps(path) for path in sorted(folder.glob("seed*.h5"))]
    fixed_h5 = folder / f"fixed_pass_{analysis_variant(config)}.h5"
    if not fixed_h5.exists():
        return []
    channel_seeds = ChannelSeeds(config, fixed_h5)
    return [channel_seeds.maps(seed) for seed in range(config["simulation"]["seeds"])]


def channel_rows(run: Path, config: dict | None = None) -> dict[str, tuple[float, float]]:
    """{channel: (noise Q/U rms, template detector-0 Q/U rms)} averaged over seeds."""
    rows = {}
    for folder in sorted((run / "results" / "maps").iterdir()):
        if not folder.is_dir():
            continue
        noise, template = [], []
        for data in seed_maps(folder, config):
            seen = data["nosys"][0] != hp.UNSEEN
            residual = data["nosys"] - data["cmb_reference"] - data["foreground_reference"]
            noise.append(qu_rms(residual, seen))
            template.append(qu_rms(data["templates"][0], seen))
        if noise:
            rows[folder.name] = (float(np.mean(noise)), float(np.mean(template)))
    return rows


def residual_bands(run: Path) -> np.ndarray:
    """Mean over seeds of the nosys HILC residual BB [K^2] per ELL_BANDS."""
    tables = [pd.read_csv(p) for p in sorted((run / "results" / "spectra").glob("seed*/nosys.csv"))]
    bb = np.mean([t["bb_residual_k2"].to_numpy() for t in tables], axis=0)
    return np.array([bb[lo:hi].mean() for lo, hi in ELL_BANDS])


def estimator_rows(run: Path) -> dict:
    """The estimators of a run: per-seed systematic-only k and the paper's delta r per
    sigma_g1 (``delta_r.csv``, grid points only), and sigma_r."""
    result = json.loads((run / "results" / "requirement.json").read_text())
    table = pd.read_csv(run / "results" / "delta_r.csv")
    table = table[~table["extended"]]
    return {
        "k": np.asarray(result["systematic_only"]["k_per_seed"]),
        "requirement": result["systematic_only"]["requirement_sigma_g1_per_k"],
        "sigma_r": result["sigma_r_fisher"],
        "paper": {sigma: group["delta_r"].to_numpy() for sigma, group in table.groupby("sigma_g1")},
    }


def mean_and_error(values: np.ndarray) -> tuple[float, float]:
    """Mean and its standard error over seeds."""
    return float(np.mean(values)), float(np.std(values, ddof=1) / np.sqrt(len(values)))


def compared(name: str, tod: np.ndarray, fast: np.ndarray) -> str:
    """A table row: mean +- error of both paths, their ratio, the difference in errors."""
    (a, da), (b, db) = mean_and_error(tod), mean_and_error(fast)
    pull = (b - a) / np.hypot(da, db)
    return f"| {name} | {a:.3g} +- {da:.2g} | {b:.3g} +- {db:.2g} | {b / a:.2f} | {pull:+.1f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tod", type=Path, required=True, help="run folder, TOD path")
    parser.add_argument("--map-domain", type=Path, required=True, help="run folder, map domain")
    parser.add_argument(
        "--configfile", nargs="+", required=True, help="the map-domain run's configuration files"
    )
    arguments = parser.parse_args()
    runs = {"tod": arguments.tod, "map_domain": arguments.map_domain}

    md_config = load_config(*arguments.configfile)
    configs = {"tod": None, "map_domain": md_config}
    channels = {name: channel_rows(run, configs.get(name)) for name, run in runs.items()}
    print(
        "| channel | noise Q/U rms tod [K] | map domain | ratio | template Q/U rms tod "
        "[K^2] | map domain | ratio |"
    )
    print("|---|---|---|---|---|---|---|")
    for channel, (noise, template) in channels["tod"].items():
        other_noise, other_template = channels["map_domain"][channel]
        template_ratio = other_template / template if template > 0 else float("nan")
        print(
            f"| {channel} | {noise:.3g} | {other_noise:.3g} | {other_noise / noise:.3f} | "
            f"{template:.3g} | {other_template:.3g} | {template_ratio:.3f} |"
        )

    bands = {name: residual_bands(run) for name, run in runs.items()}
    print(
        "\n| nosys HILC residual BB [K^2] | "
        + " | ".join(f"ell {a}-{b - 1}" for a, b in ELL_BANDS)
        + " |"
    )
    print("|---|" + "---|" * len(ELL_BANDS))
    for name, values in bands.items():
        print(f"| {name} | " + " | ".join(f"{v:.3g}" for v in values) + " |")
    ratio = bands["map_domain"] / bands["tod"]
    print("| ratio | " + " | ".join(f"{v:.3f}" for v in ratio) + " |")

    estimators = {name: estimator_rows(run) for name, run in runs.items()}
    tod, fast = estimators["tod"], estimators["map_domain"]
    print(
        "\n| quantity (mean over seeds +- its error) | tod | map domain | ratio | "
        "difference / error |"
    )
    print("|---|---|---|---|---|")
    print(compared("systematic-only k [K^2]", tod["k"], fast["k"]))
    for sigma, delta_r in tod["paper"].items():
        print(compared(f"paper's delta r at sigma_g1 = {sigma:g}", delta_r, fast["paper"][sigma]))
    print(
        f"| systematic-only requirement [1/K] | {tod['requirement']:.3g} | "
        f"{fast['requirement']:.3g} | {fast['requirement'] / tod['requirement']:.2f} | |"
    )
    print(
        f"| sigma_r | {tod['sigma_r']:.3g} | {fast['sigma_r']:.3g} | "
        f"{fast['sigma_r'] / tod['sigma_r']:.2f} | |"
    )


if __name__ == "__main__":
    main()
