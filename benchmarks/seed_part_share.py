"""The seed part's share of each systematics channel's template on a map-domain run: where
the map domain's drawn CMB x h and noise x h (validated in benchmarks/map_domain_validation.py
at one month) set the answer.

    python benchmarks/seed_part_share.py RUN --configfile config/config.yaml \
        config/one_year.yaml config/nside128.yaml --seeds 2

Per channel with systematics whose fixed pass RUN holds: the Fisher bias k_c [K^2] of the
channel's template BB (detectors 0 + 1, beam deconvolved; RUN's likelihood model, or that
of ``--model-from``) for the fixed pass's template alone, for the seed part (a seed's
template minus it) and for the whole, mean over the first ``--seeds`` seeds, and the seed
part's share of the whole.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from map_domain_validation import template_bb

from hwp_tes_systematics.analysis.likelihood import fisher_bias
from hwp_tes_systematics.analysis.noise_model import model_from_noise_csv
from hwp_tes_systematics.config import analysis_variant, load_config
from hwp_tes_systematics.simulation.map_domain import ChannelSeeds


def seed_part_share(fixed_h5: Path, config: dict, model, seeds: int) -> dict:
    """{"fixed", "seed_part", "whole": k_c [K^2], "share": seed part / whole} of a channel."""
    lmax = int(model.ell.max())
    channel_seeds = ChannelSeeds.from_run(config, fixed_h5)
    good, fixed = channel_seeds.fixed.good, channel_seeds.fixed_templates

    def k_c(templates):
        return fisher_bias(template_bb(templates, good, lmax, channel_seeds.fwhm_arcmin), model)

    whole, seed_part = [], []
    for seed in range(seeds):
        templates = np.where(good, channel_seeds.maps(seed)["templates"], 0.0)
        whole.append(k_c(templates))
        seed_part.append(k_c(templates - fixed))
    result = {"fixed": k_c(fixed), "seed_part": np.mean(seed_part), "whole": np.mean(whole)}
    return {**result, "share": result["seed_part"] / result["whole"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a map-domain run folder")
    parser.add_argument("--configfile", nargs="+", required=True, help="the run's configuration")
    parser.add_argument("--seeds", type=int, default=2, help="seeds averaged (default 2)")
    parser.add_argument(
        "--model-from", type=Path, default=None, help="run whose likelihood model to use"
    )
    arguments = parser.parse_args()
    config = load_config(*arguments.configfile)
    likelihood = config["likelihood"]
    model_run = arguments.model_from or arguments.run
    model = model_from_noise_csv(
        str(model_run / "results" / "spectra" / "noise_model.csv"),
        likelihood["lmin"],
        likelihood["lmax"],
        likelihood["model"],
    )
    print(f"# {arguments.run}, {analysis_variant(config)}, {arguments.seeds} seeds")
    print("| channel | k_c fixed pass [K^2] | seed part | whole | seed part / whole |")
    print("|---|---|---|---|---|")
    for name in config["instrument"]["systematics_channels"]:
        fixed_h5 = (
            arguments.run / "results" / "maps" / name / f"fixed_pass_{analysis_variant(config)}.h5"
        )
        if fixed_h5.exists():
            row = seed_part_share(fixed_h5, config, model, arguments.seeds)
            print(
                f"| {name} | {row['fixed']:.3g} | {row['seed_part']:.3g} | {row['whole']:.3g} "
                f"| {row['share']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
