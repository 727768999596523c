"""The requirement and the nonlinearity template versus the map resolution, with and
without baselines, from one set of fixed passes (issue 27).

    python benchmarks/resolution_study.py --run --out docs/resolution
    python benchmarks/resolution_study.py --out docs/resolution   # only gather the runs
    python benchmarks/resolution_study.py --out docs/resolution --requirements-only

For each map-maker (nside in ``--nsides``, 60 s baselines or none, binned or with
``--map-maker demodulated`` HWP-demodulated), the workflow's configuration is
``--configfile`` (default config/one_year.yaml config/resolution_study.yaml) +
``config/nside<N>.yaml`` (+ ``config/no_baselines.yaml``, + ``config/demodulated.yaml``): with
config/resolution_study.yaml they share one fixed TOD pass per channel
(simulation.fixed_pass_*), so the first
run makes the passes and each other only its seeds' a_lm and the analysis. ``--run``
runs them one after another in this folder (``snakemake --cores N results/requirement.json``)
and copies each run's small outputs (requirement.json, delta_r.csv, noise_model.csv,
residual_bb_means.csv, Fig. 8) to ``--out``/<variant>/, with its wall time. The rows
gathered replace those of the same map-makers in ``--out``'s CSV; the others are kept.

Then, per map-maker: the requirement in both conventions (the 68 %-point shift, the
paper's, and the Fisher peak shift) with their bootstrap errors, sigma_r, whether the
model describes the data, the paper estimator's crossing; and per channel of
``--channels`` the total template of detector 0 (sum of the three terms of d^2 at the
channel's A_2, each seed's maps made again from the fixed pass as the map_domain_alms job
makes them) as BB pseudo-spectra on its observed pixels in ell 2-12, 13-40, 41-128,
mean over ``--template-seeds`` seeds, and the same for each term of its fixed part (no
seed; columns ``fixed_ss``, ``fixed_sh``, ``fixed_hh``: T_ss, 2 A_2 T_sh, A_2^2 T_hh).
Why it moves: per resolution, the pixel size, the time a detector takes to cross a pixel
(spin rate x sin(spin-boresight angle), PTEP scanning) and the HWP turns in that time,
and the crossings per observed pixel (hits over samples per crossing, from the fixed
pass). Writes ``resolution_study.json``, ``resolution_study.csv`` and
``resolution_study.png``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import time
from pathlib import Path

import healpy as hp
import numpy as np
import pandas as pd

from hwp_tes_systematics import config as cfg
from hwp_tes_systematics.analysis.spectra import pseudo_spectra
from hwp_tes_systematics.simulation.fixed_maps import read_fixed_field
from hwp_tes_systematics.simulation.map_domain import ChannelSeeds
from hwp_tes_systematics.simulation.tod_maps import TEMPLATE_TERMS, term_weights

BANDS = ((2, 12), (13, 40), (41, 128))
SPIN_RATE_HZ = 3.0 / 3600  # PTEP: 3 spin rotations per hour (litebird_sim's scanning_parameters)
SPIN_BORESIGHT_DEG = 50.0  # PTEP: angle between the spin axis and the boresight (MFT/HFT)
PAPER_REQUIREMENT = 2e-3  # K^-1, Micheli et al. 2024
CONVENTIONS = (  # (column key, marker, colour, label) of the two delta r conventions
    ("68", "o", "C0", "68 % point (paper's delta r)"),
    ("fisher", "s", "C2", "Fisher peak shift"),
)
KEPT = ("requirement.json", "delta_r.csv", "spectra/noise_model.csv")
KEPT += ("spectra/residual_bb_means.csv", "figures/fig8_requirement.png")


def variant_configs(
    base: list[str], nside: int, baseline: float | None, map_maker: str = "binned"
) -> list[str]:
    files = [*base, f"config/nside{nside}.yaml"]
    files += ["config/no_baselines.yaml"] if baseline is None else []
    return files + (["config/demodulated.yaml"] if map_maker == "demodulated" else [])


def run_variant(files: list[str], cores: int, out: Path) -> float:
    """Run the workflow for one map-maker; copy its small outputs to ``out``; wall [s]."""
    started = time.perf_counter()
    # every kept file a target: the residual spectra's means and Fig. 8 are not
    # inputs of requirement.json
    targets = [f"results/{name}" for name in KEPT]
    command = ["snakemake", "--cores", str(cores), *targets]
    subprocess.run([*command, "--configfile", "config/config.yaml", *files], check=True)
    wall_s = time.perf_counter() - started
    out.mkdir(parents=True, exist_ok=True)
    for name in KEPT:
        shutil.copy(Path("results") / name, out / Path(name).name)
    (out / "run.json").write_text(json.dumps({"configfiles": files, "wall_s": wall_s}, indent=1))
    return wall_s


REQUIREMENT_KEYS = (
    "consistent",
    "sigma_r",
    "requirement_68_per_k",
    "requirement_68_error_per_k",
    "requirement_fisher_per_k",
    "requirement_fisher_error_per_k",
    "paper_estimator_crossing_per_k",
)


def requirement_row(folder: Path) -> dict:
    result = json.loads((folder / "requirement.json").read_text())
    headline = result["headline"]
    return {
        "consistent": headline["consistent"],
        "sigma_r": headline["sigma_r_fisher"],
        "requirement_68_per_k": headline["requirement_sigma_g1_per_k"],
        "requirement_68_error_per_k": headline["error_per_k"],
        "requirement_fisher_per_k": headline["fisher_peak_shift_requirement_sigma_g1_per_k"],
        "requirement_fisher_error_per_k": headline["fisher_peak_shift_error_per_k"],
        "paper_estimator_crossing_per_k": headline["paper_estimator_budget_crossing_per_k"],
    }


def with_requirements(table: pd.DataFrame, out: Path) -> pd.DataFrame:
    """The table with each map-maker's requirement columns read again from
    ``out``/<variant>/requirement.json where that analysis has been run (the templates
    kept as they are)."""
    table = table.copy()
    table["consistent"] = table["consistent"].astype(object)  # bool where run, NaN elsewhere
    for index, variant in table["variant"].items():
        folder = out / variant
        if (folder / "requirement.json").exists():
            for key, value in requirement_row(folder).items():
                table.loc[index, key] = value
    return table


def band_means(map_iqu: np.ndarray, good: np.ndarray) -> list[float]:
    """BB pseudo-spectrum of a map on its ``good`` pixels (over the observed fraction)
    averaged over each of BANDS."""
    lmax = BANDS[-1][1]
    alm = hp.map2alm(np.where(good, map_iqu, 0.0), lmax=lmax, iter=0)
    bb = pseudo_spectra(alm, lmax, good.mean())[2]
    return [float(bb[first : last + 1].mean()) for first, last in BANDS]


def template_bands(config: dict, fixed_h5: Path, seeds: int) -> tuple[list[float], dict]:
    """Mean over seeds of detector 0's total template BB [K_CMB^2 K^2] per BANDS, and the
    BB per BANDS of each term of its fixed part (no seed: foregrounds and dipole),
    ``s*s`` (T_ss), ``s*h`` (2 A_2 T_sh) and ``h*h`` (A_2^2 T_hh), by term name."""
    channel_seeds = ChannelSeeds.from_run(config, fixed_h5)
    good = channel_seeds.fixed.good
    spectra = [band_means(channel_seeds.maps(seed)["templates"][0], good) for seed in range(seeds)]
    weights = term_weights(float(channel_seeds.attributes["a2_k_cmb"]))
    terms = channel_seeds.fixed.template_terms[:, 0]  # detector 0's three terms
    fixed_terms = {
        name: band_means(weight * term, good)
        for name, weight, term in zip(TEMPLATE_TERMS, weights, terms, strict=True)
    }
    return list(np.mean(spectra, axis=0)), fixed_terms


def crossing_numbers(fixed_h5: Path, nside: int, hwp_hz: float, rate_hz: float) -> dict:
    """Pixel size, crossing time, HWP turns per crossing, crossings per observed pixel."""
    pixel_rad = hp.nside2resol(nside)
    speed_rad_s = 2 * np.pi * SPIN_RATE_HZ * np.sin(np.radians(SPIN_BORESIGHT_DEG))
    crossing_s = pixel_rad / speed_rad_s
    hits = read_fixed_field(fixed_h5, "hits")
    observed = hits[hits > 0]
    return {
        "pixel_arcmin": float(np.degrees(pixel_rad) * 60),
        "crossing_s": float(crossing_s),
        "hwp_turns_per_crossing": float(crossing_s * hwp_hz),
        "crossings_per_pixel": float(np.mean(observed) / (2 * crossing_s * rate_hz)),
    }


def plot(table: pd.DataFrame, channels: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(12, 4.8))
    styles = {(True, "binned"): "-", (False, "binned"): "--"}
    styles |= {(True, "demodulated"): "-.", (False, "demodulated"): ":"}
    table = table.assign(map_maker=table.get("map_maker", "binned"))
    for (baselines, map_maker), group in table.groupby(["baselines", "map_maker"]):
        group = group.sort_values("nside")
        label = "60 s baselines" if baselines else "no baselines"
        label += ", demodulated" if map_maker == "demodulated" else ""
        style = styles[baselines, map_maker]
        for channel, marker in zip(channels, "os^v", strict=False):
            for (first, last), colour in zip(BANDS[::2], ("C0", "C3"), strict=True):
                column = f"template_bb_{channel}_ell{first}_{last}"
                if column in group:
                    left.plot(
                        group["nside"],
                        group[column],
                        style,
                        marker=marker,
                        color=colour,
                        label=f"{channel}, ell {first}-{last}, {label}",
                    )
        for key, marker, colour, convention in CONVENTIONS:
            if not group[f"requirement_{key}_per_k"].notna().any():
                continue  # that map-maker's analysis not run yet
            right.errorbar(
                group["nside"],
                group[f"requirement_{key}_per_k"],
                group[f"requirement_{key}_error_per_k"],
                fmt=style + marker,
                color=colour,
                capsize=3,
                label=f"{convention}, {label}",
            )
    right.axhline(PAPER_REQUIREMENT, color="k", lw=1, ls=":", label="Micheli et al. 2024")
    if not np.isfinite(table["requirement_68_per_k"].to_numpy(float)).any():
        right.text(0.5, 0.6, "analyses not yet run", transform=right.transAxes, ha="center")
        right.set_ylim(1e-4, 1e-1)
    nsides = sorted(table["nside"].unique())
    for axis in (left, right):
        axis.set_xscale("log", base=2)
        axis.set_yscale("log")
        axis.set_xlim(nsides[0] / 1.4, nsides[-1] * 1.4)
        axis.set_xlabel("nside")
        axis.set_xticks(sorted(table["nside"].unique()))
        axis.get_xaxis().set_major_formatter(matplotlib.ticker.ScalarFormatter())
    left.set_ylabel("template BB of detector 0 [K_CMB^2 K^2]")
    left.set_title("nonlinearity template")
    right.set_ylabel("requirement on sigma_g1 [K^-1]")
    right.set_title("requirement (transfer in the model)")
    for axis in (left, right):
        axis.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    figure.tight_layout()
    figure.savefig(path, dpi=120, bbox_inches="tight")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--configfile",
        nargs="+",
        default=["config/one_year.yaml", "config/resolution_study.yaml"],
    )
    parser.add_argument("--nsides", type=int, nargs="+", default=[512, 256, 128, 64])
    parser.add_argument("--baselines", choices=("both", "with", "without"), default="both")
    parser.add_argument("--map-maker", choices=("binned", "demodulated"), default="binned")
    parser.add_argument("--channels", nargs="+", default=["M1-140", "H3-402"])
    parser.add_argument("--template-seeds", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--run", action="store_true", help="run the workflow for each")
    parser.add_argument(
        "--replot", action="store_true", help="only redraw the figure from the CSV in --out"
    )
    parser.add_argument(
        "--requirements-only",
        action="store_true",
        help="fill the CSV's requirement columns from the analyses in --out/<variant>/ "
        "(templates not recomputed), then redraw",
    )
    arguments = parser.parse_args()
    if arguments.replot or arguments.requirements_only:
        table = pd.read_csv(arguments.out / "resolution_study.csv")
        if arguments.requirements_only:
            table = with_requirements(table, arguments.out)
            table.to_csv(arguments.out / "resolution_study.csv", index=False)
            document = json.loads((arguments.out / "resolution_study.json").read_text())
            document["rows"] = table.astype(object).where(table.notna(), None).to_dict("records")
            (arguments.out / "resolution_study.json").write_text(json.dumps(document, indent=1))
        plot(table, arguments.channels, arguments.out / "resolution_study.png")
        return
    baselines = {"both": [60.0, None], "with": [60.0], "without": [None]}[arguments.baselines]
    rows = []
    for nside in arguments.nsides:
        for baseline in baselines:
            files = variant_configs(arguments.configfile, nside, baseline, arguments.map_maker)
            config = cfg.load_config("config/config.yaml", *files)
            variant = cfg.analysis_variant(config)
            folder = arguments.out / variant
            if arguments.run:
                wall_s = run_variant(files, arguments.cores, folder)
                print(f"{variant}: {wall_s / 60:.1f} min", flush=True)
            row = {"variant": variant, "nside": nside, "baselines": baseline is not None}
            row["map_maker"] = arguments.map_maker
            if (folder / "requirement.json").exists():
                row.update(requirement_row(folder))
            else:
                print(f"{variant}: no analysis in {folder} (run with --run): templates only")
                row.update(dict.fromkeys(REQUIREMENT_KEYS, np.nan))
            for channel in arguments.channels:
                fixed_h5 = Path(f"results/maps/{channel}/fixed_pass_{variant}.h5")
                if not fixed_h5.exists():
                    continue
                bands, fixed_terms = template_bands(config, fixed_h5, arguments.template_seeds)
                for (first, last), value in zip(BANDS, bands, strict=True):
                    row[f"template_bb_{channel}_ell{first}_{last}"] = value
                for term, term_bands in fixed_terms.items():
                    for (first, last), value in zip(BANDS, term_bands, strict=True):
                        label = term.replace("*", "")  # s*h -> sh
                        row[f"fixed_{label}_bb_{channel}_ell{first}_{last}"] = value
                hwp_hz = cfg.channel(config, channel).hwp_frequency_hz
                rate_hz = config["simulation"]["sampling_rate_hz"]
                for key, value in crossing_numbers(fixed_h5, nside, hwp_hz, rate_hz).items():
                    row[f"{key}_{channel}"] = value
            measured = not np.isnan(row["sigma_r"]) or any(k.startswith("template") for k in row)
            if measured:
                rows.append(row)
    if not rows:
        raise SystemExit("no map-maker has results: nothing to gather")
    table = pd.DataFrame(rows)
    arguments.out.mkdir(parents=True, exist_ok=True)
    gathered = arguments.out / "resolution_study.csv"
    if gathered.exists():  # keep the rows of the map-makers not gathered now
        earlier = pd.read_csv(gathered)
        earlier = earlier.assign(map_maker=earlier.get("map_maker", "binned"))
        table = pd.concat([earlier[~earlier["variant"].isin(table["variant"])], table])
        table = table.reset_index(drop=True)
    table.to_csv(gathered, index=False)
    document = table.astype(object).where(table.notna(), None).to_dict("records")
    (arguments.out / "resolution_study.json").write_text(
        json.dumps({"configfiles": arguments.configfile, "rows": document}, indent=1)
    )
    plot(table, arguments.channels, arguments.out / "resolution_study.png")
    columns = ["variant", "sigma_r", "requirement_68_per_k", "requirement_fisher_per_k"]
    columns += [c for c in table.columns if c.startswith(("template_bb", "hwp_turns", "crossings"))]
    print(table[columns].to_markdown(index=False, floatfmt=".3g"))


if __name__ == "__main__":
    main()
