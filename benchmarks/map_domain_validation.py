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
   ratio and their difference in units of the combined error; sigma_r;
4. per channel with systematics, what sets the answer: the Fisher bias k_c of the
   channel's own template BB (detectors 0 and 1 at unit g1, the expectation over the g1
   draws, beam deconvolved) through the TOD run's likelihood model, for the whole
   template and for its seed part alone (the template minus the fixed pass's, i.e. the
   CMB x h and noise x h terms), both paths, mean over seeds with its error;
5. with ``--split``, the seed part in its two pieces: k_c of CMB x h (the map domain's
   M^-1 H_k CMB, the same seed's CMB on both paths) and of noise x h (the map domain's
   draw; on the TOD path the seed part minus the map domain's CMB x h), and per multipole
   band the noise x h BB of each path over the map domain's unshaped draw M^-1 c_k: the
   filter's action on h n that each path has (the TOD's is the truth, the map domain's
   is its shaping S_ell).

To validate where the seed part matters (issue 26), run both at one-year noise depth:
``config/one_year.yaml config/map_domain_validation.yaml`` (one month, the noise scaled
to one year's per pixel) and the same + ``config/tod_path.yaml``.

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

from hwp_tes_systematics.analysis.likelihood import BBModel, fisher_bias
from hwp_tes_systematics.analysis.noise_model import model_from_noise_csv
from hwp_tes_systematics.analysis.spectra import pseudo_spectra
from hwp_tes_systematics.config import analysis_variant, load_config
from hwp_tes_systematics.simulation.map_domain import ChannelSeeds
from hwp_tes_systematics.simulation.maps_file import read_channel_maps
from hwp_tes_systematics.sky.cmb import band_limited_seed_cmb

ELL_BANDS = ((2, 12), (12, 40), (40, 80), (80, 129))


def qu_rms(maps: np.ndarray, seen: np.ndarray) -> float:
    return float(np.sqrt(np.mean(maps[1:, seen] ** 2)))


def seed_maps(folder: Path, config: dict | None, seeds=None):
    """Each seed's maps of a channel: its maps files (TOD path; the seeds ``seeds``, by
    default all there are), or made from its fixed pass (map-domain path, ``config``
    given; by default seeds 0 to simulation.seeds - 1)."""
    if config is None:
        paths = sorted(folder.glob("seed*.h5"), key=lambda p: int(p.stem[4:]))
        if seeds is not None:
            paths = [folder / f"seed{seed}.h5" for seed in seeds]
            paths = [path for path in paths if path.exists()]
        return [read_channel_maps(path) for path in paths]
    fixed_h5 = folder / f"fixed_pass_{analysis_variant(config)}.h5"
    if not fixed_h5.exists():
        return []
    channel_seeds = ChannelSeeds.from_run(config, fixed_h5)
    return [channel_seeds.maps(seed) for seed in seed_list(config, seeds)]


def seed_list(config: dict, seeds=None) -> list[int]:
    """``seeds``, or 0 to simulation.seeds - 1."""
    return list(range(config["simulation"]["seeds"])) if seeds is None else list(seeds)


def channel_rows(
    run: Path, config: dict | None = None, seeds=None, channels=None
) -> dict[str, tuple[float, float]]:
    """{channel: (noise Q/U rms, template detector-0 Q/U rms)} averaged over ``seeds``, for
    ``channels`` (default: every channel folder of the run)."""
    rows = {}
    for folder in sorted((run / "results" / "maps").iterdir()):
        if not folder.is_dir() or (channels is not None and folder.name not in channels):
            continue
        noise, template = [], []
        for data in seed_maps(folder, config, seeds):
            seen = data["nosys"][0] != hp.UNSEEN
            residual = data["nosys"] - data["cmb_reference"] - data["foreground_reference"]
            noise.append(qu_rms(residual, seen))
            template.append(qu_rms(data["templates"][0], seen))
        if noise:
            rows[folder.name] = (float(np.mean(noise)), float(np.mean(template)))
    return rows


def template_bb(templates: np.ndarray, good: np.ndarray, lmax: int, fwhm_arcmin: float):
    """sum_k BB of detector k's template [K_CMB^2 K^2] on ``good``, beam deconvolved:
    the expectation over independent unit g1 draws of BB(sum_k g1_k T_k)."""
    beam_bb = hp.gauss_beam(np.radians(fwhm_arcmin / 60), lmax=lmax, pol=True)[:, 2]
    total = np.zeros(lmax + 1)
    for template in templates:
        alm = hp.map2alm(np.where(good, template, 0.0), lmax=lmax, iter=0)
        total += pseudo_spectra(alm, lmax, good.mean())[2]
    return total / beam_bb**2


def channel_biases(tod_run: Path, md_run: Path, config: dict, model: BBModel, seeds=None) -> dict:
    """{(channel, path): {"total": k_c per seed, "seed_part": k_c per seed}} of the
    channels with systematics, path "tod" or "map_domain": the Fisher bias of the
    channel's template BB (:func:`template_bb`) and of its seed part (the template minus
    the map-domain run's fixed pass's; the same operator on both paths, so the rest is the
    seed's CMB x h and noise x h) [K^2]. ``config``: the map-domain run's; ``seeds``: the
    realizations compared (default 0 to simulation.seeds - 1; a TOD seed missing is left
    out on both paths)."""
    lmax = int(model.ell.max())
    biases = {}
    for name in config["instrument"]["systematics_channels"]:
        folder = md_run / "results" / "maps" / name
        fixed_h5 = folder / f"fixed_pass_{analysis_variant(config)}.h5"
        if not fixed_h5.exists():
            continue
        channel_seeds = ChannelSeeds.from_run(config, fixed_h5)
        fixed, fixed_templates = channel_seeds.fixed, channel_seeds.fixed_templates
        fwhm = channel_seeds.fwhm_arcmin
        tod_folder = tod_run / "results" / "maps" / name
        held = [s for s in seed_list(config, seeds) if (tod_folder / f"seed{s}.h5").exists()]
        if len(held) < 2:
            continue
        tod_seeds = seed_maps(tod_folder, None, held)
        md_seeds = (channel_seeds.maps(seed) for seed in held)
        for path, realizations in (("tod", tod_seeds), ("map_domain", md_seeds)):
            rows = {"total": [], "seed_part": []}
            for data in realizations:
                templates = np.where(fixed.good, data["templates"], 0.0)
                for key, maps in (("total", templates), ("seed_part", templates - fixed_templates)):
                    rows[key].append(fisher_bias(template_bb(maps, fixed.good, lmax, fwhm), model))
            biases[(name, path)] = {key: np.asarray(values) for key, values in rows.items()}
    return biases


def seed_part_pieces(tod_run: Path, md_run: Path, config: dict, model: BBModel, seeds=None) -> dict:
    """{channel: {"k": {piece: k_c per seed}, "bb": {piece: mean BB over seeds}}} of the
    seed part's pieces (module docstring, item 5): pieces "cmb_h" and "noise_h_md",
    "noise_h_tod"; "bb" also holds "noise_h_unshaped" (the map domain's M^-1 c_k)."""
    lmax = int(model.ell.max())
    master_seed, simulation = config["master_seed"], config["simulation"]
    pieces = {}
    for name in config["instrument"]["systematics_channels"]:
        fixed_h5 = md_run / "results" / "maps" / name / f"fixed_pass_{analysis_variant(config)}.h5"
        if not fixed_h5.exists():
            continue
        channel_seeds = ChannelSeeds.from_run(config, fixed_h5)
        good = channel_seeds.fixed.good
        pixels = np.flatnonzero(good)
        a2 = float(channel_seeds.attributes["a2_k_cmb"])
        fixed_templates, fwhm = channel_seeds.fixed_templates, channel_seeds.fwhm_arcmin
        tod_folder = tod_run / "results" / "maps" / name
        held = [s for s in seed_list(config, seeds) if (tod_folder / f"seed{s}.h5").exists()]
        if len(held) < 2:
            continue
        tod_seeds = seed_maps(tod_folder, None, held)
        k_rows = {"cmb_h": [], "noise_h_md": [], "noise_h_tod": []}
        bb_rows = {"noise_h_md": [], "noise_h_tod": [], "noise_h_unshaped": []}
        for seed, tod_data in zip(held, tod_seeds, strict=True):
            md_data = channel_seeds.maps(seed)
            operators = channel_seeds.operators
            cmb_alm, band = band_limited_seed_cmb(
                channel_seeds.lmax, simulation["cmb_r"], master_seed, seed, fwhm
            )
            cmb = hp.alm2map(cmb_alm, hp.npix2nside(good.size), lmax=band, pixwin=False)
            _, c = operators.noise.draw(channel_seeds.noise_generator(seed))  # md_data's h n
            cmb_h, unshaped = np.zeros_like(fixed_templates), np.zeros_like(fixed_templates)
            for k, h_k in enumerate(operators.h_matrices):
                product = np.einsum("pij,jp->ip", h_k, cmb[:, pixels])
                cmb_h[k][:, pixels] = 2 * a2 * operators.solve(product)
                unshaped[k][:, pixels] = 2 * a2 * operators.solve(c[k][:, pixels])
            maps = {
                "cmb_h": cmb_h,
                "noise_h_md": np.where(good, md_data["templates"], 0.0) - fixed_templates - cmb_h,
                "noise_h_tod": np.where(good, tod_data["templates"], 0.0) - fixed_templates - cmb_h,
                "noise_h_unshaped": unshaped,
            }
            spectra = {
                key: template_bb(np.where(good, value, 0.0), good, lmax, fwhm)
                for key, value in maps.items()
            }
            for key, values in k_rows.items():
                values.append(fisher_bias(spectra[key], model))
            for key, values in bb_rows.items():
                values.append(spectra[key])
        pieces[name] = {
            "k": {key: np.asarray(values) for key, values in k_rows.items()},
            "bb": {key: np.mean(values, axis=0) for key, values in bb_rows.items()},
        }
    return pieces


def print_seed_part_pieces(pieces: dict) -> None:
    """The tables of item 5 (module docstring)."""
    print(
        "\n| seed part's pieces: k_c [K^2] (mean over seeds +- its error) | tod | map domain "
        "| ratio | difference / error |"
    )
    print("|---|---|---|---|---|")
    for name, piece in pieces.items():
        k = piece["k"]
        cmb, error = mean_and_error(k["cmb_h"])
        print(f"| {name}, CMB x h (the same on both paths) | {cmb:.3g} +- {error:.2g} | | | |")
        print(compared(f"{name}, noise x h", k["noise_h_tod"], k["noise_h_md"]))
    bands = ((2, 12), (12, 24), (24, 40), (40, 60), (60, 80), (80, 129))
    print_band_header("noise x h BB over the unshaped draw (the filter's action on h n)", bands)
    for name, piece in pieces.items():
        bb = piece["bb"]
        for key, label in (("noise_h_tod", "TOD"), ("noise_h_md", "map domain")):
            ratios = [bb[key][a:b].mean() / bb["noise_h_unshaped"][a:b].mean() for a, b in bands]
            print(f"| {name}, {label} | " + " | ".join(f"{r:.3f}" for r in ratios) + " |")


def print_per_seed(biases: dict) -> None:
    """Each seed's seed-part k_c on both paths, and the ratio of their variances over
    seeds (the map domain's draws should scatter as the TOD's)."""
    print("\n| channel, path | seed part k_c [K^2] per seed | std / mean |")
    print("|---|---|---|")
    for name in dict.fromkeys(name for name, _ in biases):
        for path in ("tod", "map_domain"):
            values = biases[(name, path)]["seed_part"]
            listed = ", ".join(f"{v:.3g}" for v in values)
            print(f"| {name}, {path} | {listed} | {np.std(values, ddof=1) / np.mean(values):.3f} |")
        ratio = np.var(biases[(name, "tod")]["seed_part"], ddof=1) / np.var(
            biases[(name, "map_domain")]["seed_part"], ddof=1
        )
        print(f"| {name}, variance TOD / map domain | {ratio:.2f} | |")


def print_band_header(title: str, bands) -> None:
    """A Markdown table's header: ``title``, then one column per multipole band (lo, hi)."""
    print(f"\n| {title} | " + " | ".join(f"ell {a}-{b - 1}" for a, b in bands) + " |")
    print("|---|" + "---|" * len(bands))


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
    parser.add_argument(
        "--split",
        action="store_true",
        help="also split the seed part into CMB x h and noise x h (item 5)",
    )
    parser.add_argument(
        "--seeds",
        nargs=2,
        type=int,
        metavar=("FIRST", "LAST"),
        help="compare the realizations FIRST..LAST (default: 0 to simulation.seeds - 1), "
        "e.g. held-out TOD seeds",
    )
    parser.add_argument(
        "--per-seed",
        action="store_true",
        help="also list each seed's seed-part k_c on both paths (their scatter)",
    )
    parser.add_argument(
        "--noise-model",
        type=Path,
        help="the noise_model.csv whose likelihood model weighs k_c (default: either run's)",
    )
    arguments = parser.parse_args()
    runs = {"tod": arguments.tod, "map_domain": arguments.map_domain}
    seeds = None if arguments.seeds is None else range(arguments.seeds[0], arguments.seeds[1] + 1)

    md_config = load_config(*arguments.configfile)
    if seeds is None:
        seeds = range(md_config["simulation"]["seeds"])
    channels = {"tod": channel_rows(runs["tod"], None, seeds)}
    channels["map_domain"] = channel_rows(runs["map_domain"], md_config, seeds, channels["tod"])
    print(
        "| channel | noise Q/U rms tod [K] | map domain | ratio | template Q/U rms tod "
        "[K^2] | map domain | ratio |"
    )
    print("|---|---|---|---|---|---|---|")
    for channel, (noise, template) in channels["tod"].items():
        if channel not in channels["map_domain"]:  # no fixed pass of this channel
            continue
        other_noise, other_template = channels["map_domain"][channel]
        template_ratio = other_template / template if template > 0 else float("nan")
        print(
            f"| {channel} | {noise:.3g} | {other_noise:.3g} | {other_noise / noise:.3f} | "
            f"{template:.3g} | {other_template:.3g} | {template_ratio:.3f} |"
        )

    if arguments.seeds is not None:
        print("\n(--seeds: the HILC-level comparison, over the runs' own seeds, is left out)")
    elif not all((run / "results" / "requirement.json").exists() for run in runs.values()):
        print("\n(one run has no analysis: the HILC-level comparison is left out)")
    else:
        analysis_tables(runs)

    likelihood = md_config["likelihood"]
    candidates = [run / "results" / "spectra" / "noise_model.csv" for run in runs.values()]
    if arguments.noise_model is not None:
        candidates = [arguments.noise_model]
    analysed = next((path for path in candidates if path.exists()), None)
    if analysed is None:
        parser.error(f"no likelihood model: none of {[str(p) for p in candidates]} exists")
    model = model_from_noise_csv(
        str(analysed),
        likelihood["lmin"],
        likelihood["lmax"],
        likelihood["model"],
    )
    biases = channel_biases(arguments.tod, arguments.map_domain, md_config, model, seeds)
    print(
        "\n| channel's own template: Fisher bias k_c [K^2] (mean over seeds +- its error; "
        f"the likelihood model of {analysed}) | tod | map domain | ratio | difference / error |"
    )
    print("|---|---|---|---|---|")
    for name in dict.fromkeys(name for name, _ in biases):
        for key in ("total", "seed_part"):
            label = f"{name}, {'whole template' if key == 'total' else 'seed part'}"
            tod_k = biases[(name, "tod")][key]
            print(compared(label, tod_k, biases[(name, "map_domain")][key]))
    if arguments.per_seed:
        print_per_seed(biases)
    if arguments.split:
        print_seed_part_pieces(
            seed_part_pieces(arguments.tod, arguments.map_domain, md_config, model, seeds)
        )


def analysis_tables(runs: dict) -> None:
    """The HILC-level comparison: residual BB bands, k and the paper's delta r, sigma_r."""
    bands = {name: residual_bands(run) for name, run in runs.items()}
    print_band_header("nosys HILC residual BB [K^2]", ELL_BANDS)
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
