"""Command line: ``python -m hwp_tes_systematics <command>``.

config-reference                      print the configuration reference (Markdown)
effect-catalog                        print the diagnosis's effect catalog (Markdown)
figure8 REQUIREMENT.json --out PNG    redraw Fig. 8 from a run's requirement.json and
                                      the delta_r.csv beside it
diagnose RECORDING.h5 --sky SKY.fits [--config FILE] --out DIR
                                      locate, name, fit and report what the
                                      simulation left out of a recording

Works from any folder: the embedded default configuration (the repository's
config/config.yaml) and its HWP curve tables ship with the package; each
--config FILE is merged over it.
"""

from __future__ import annotations

import argparse
import logging
import sys

from .config import ConfigError, config_reference_markdown, default_config_path, load_config

log = logging.getLogger("hwp_tes_systematics")


def run_diagnose(
    recording_path: str,
    sky_path: str,
    config_paths: list[str],
    out_dir: str,
    threshold: float,
    workers: int = 1,
    a2_k: float | None = None,
    requirement: str | None = None,
    memory_gb: float | None = None,
    segment_hours: float | None = None,
):
    """Diagnose one recording with the nominal HWPSS and noise of the configured instrument.

    ``a2_k`` (``--a2``) overrides the instrument model's A_2; a channel the model does not
    know (a lab detector) needs it (see :func:`.diagnose.recording.nominal_a2`).
    ``requirement`` (``--requirement``): the requirement.json a found nonlinearity is
    compared with (default: the shipped one-year result). A recording whose diagnosis
    would not fit ``memory_gb`` (default: the available memory), or any recording with
    ``segment_hours``, is diagnosed in segments (:mod:`.diagnose.segments`).
    """
    from .diagnose import diagnose
    from .diagnose.recording import MIN_SAMPLES, nominal_a2, read_recording, recording_size
    from .diagnose.segments import diagnose_segments, needs_segments
    from .simulation.channel_inputs import channel_a2_k_cmb

    config = load_config(*config_paths)
    budget = None if memory_gb is None else memory_gb * 2**30
    n_detectors, n_samples, rate_hz = recording_size(recording_path)
    segmented = segment_hours is not None or needs_segments(n_detectors, n_samples, budget)
    head = (  # a segmented recording: its first samples give the metadata
        read_recording(recording_path, budget, samples=(0, MIN_SAMPLES))
        if segmented
        else read_recording(recording_path, budget)
    )
    a2_k = nominal_a2(head, a2_k, lambda channel: channel_a2_k_cmb(config, channel))
    log.info(
        "%s: channel %s, %d detectors, %.2f h%s; nominal A_2 = %.4g K_CMB",
        recording_path,
        head.channel,
        head.n_detectors,
        n_samples / rate_hz / 3600,
        ", in segments" if segmented else "",
        a2_k,
    )
    options = {"delta_bic_threshold": threshold, "workers": workers, "requirement": requirement}
    if segmented:
        return diagnose_segments(
            recording_path,
            sky_path,
            a2_k,
            out_dir=out_dir,
            segment_hours=segment_hours,
            memory_budget_bytes=budget,
            **options,
        )
    return diagnose(head, sky_path, a2_k, out_dir=out_dir, **options)


def redraw_figure8(requirement_json: str, delta_r_csv: str | None, out_png: str) -> int:
    """Fig. 8 from a run's requirement.json and delta r table; 2 with a message naming the
    file when one is missing or is not what the requirement stage writes."""
    import json
    from pathlib import Path

    import pandas as pd

    from .analysis.requirement import plot_requirement_from_results

    requirement_path = Path(requirement_json)
    table_path = (
        requirement_path.with_name("delta_r.csv") if delta_r_csv is None else Path(delta_r_csv)
    )
    try:
        output = json.loads(requirement_path.read_text())
        table = pd.read_csv(table_path)
        written = plot_requirement_from_results(output, table, out_png)
    except FileNotFoundError as error:
        print(f"figure8: no such file: {error.filename}", file=sys.stderr)
        return 2
    except (KeyError, ValueError) as error:
        print(
            f"figure8: {requirement_path} and {table_path} are not a requirement stage's "
            f"requirement.json and delta_r.csv ({type(error).__name__}: {error})",
            file=sys.stderr,
        )
        return 2
    print(written)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m hwp_tes_systematics",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("config-reference", help="print the configuration reference (Markdown)")
    commands.add_parser(
        "effect-catalog", help="print the diagnosis's effect catalog (Markdown), from the code"
    )
    figure8 = commands.add_parser(
        "figure8",
        help="redraw Fig. 8 (delta r versus sigma_g1) from a run's requirement.json and the "
        "delta_r.csv beside it (e.g. a committed run under docs/)",
    )
    figure8.add_argument("requirement", help="a run's results/requirement.json")
    figure8.add_argument(
        "--delta-r", default=None, help="its delta r table (default: delta_r.csv beside it)"
    )
    figure8.add_argument("--out", required=True, help="the PNG to write")
    diagnose = commands.add_parser(
        "diagnose", help="find, name and fit what the simulation left out of a recording"
    )
    diagnose.add_argument("recording", help="litebird_sim HDF5 observation file")
    diagnose.add_argument(
        "--sky", required=True, help="HEALPix I, Q, U FITS map, K_CMB, Galactic (RING)"
    )
    diagnose.add_argument(
        "--config",
        action="append",
        default=[],
        help="configuration file merged over the embedded default (config/config.yaml, "
        "shipped with the package); repeatable, later files win",
    )
    diagnose.add_argument("--out", required=True, help="output folder")
    diagnose.add_argument(
        "--delta-bic",
        type=float,
        default=-10.0,
        help="an effect is kept if it lowers the BIC by more (default -10)",
    )
    diagnose.add_argument(
        "--a2",
        type=float,
        default=None,
        help="nominal HWPSS amplitude A_2 [K_CMB]: overrides the instrument model's; needed "
        "for a channel not in it (a lab detector)",
    )
    diagnose.add_argument(
        "--requirement",
        default=None,
        help="a workflow run's results/requirement.json: a nonlinearity found is compared "
        "with its requirement on sigma_g1 (default: the shipped one-year result)",
    )
    diagnose.add_argument(
        "--memory-gb",
        type=float,
        default=None,
        help="memory the diagnosis may use [GiB] (default: the available memory); a longer "
        "recording is diagnosed in segments that fit it",
    )
    diagnose.add_argument(
        "--segment-hours",
        type=float,
        default=None,
        help="diagnose in segments of at most this many hours, combined in one report",
    )
    arguments = parser.parse_args(argv)

    if arguments.command == "config-reference":
        sys.stdout.write(config_reference_markdown())
        return 0
    if arguments.command == "effect-catalog":
        from .diagnose.catalog import effect_catalog_markdown

        sys.stdout.write(effect_catalog_markdown())
        return 0
    if arguments.command == "figure8":
        return redraw_figure8(arguments.requirement, arguments.delta_r, arguments.out)

    from .io import setup_logging

    setup_logging()
    try:
        result = run_diagnose(
            arguments.recording,
            arguments.sky,
            [str(default_config_path()), *arguments.config],
            arguments.out,
            arguments.delta_bic,
            a2_k=arguments.a2,
            requirement=arguments.requirement,
            memory_gb=arguments.memory_gb,
            segment_hours=arguments.segment_hours,
        )
    except (ConfigError, ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if result.get("segments"):
        print(f"diagnosed in {len(result['segments'])} segments (see diagnosis.md)")
    if result["mismatch_found"]:
        names = ", ".join(effect["name"] for effect in result["effects"])
        print(
            f"mismatch found: {names}; chi2 {result['chi2_before']:.1f} -> "
            f"{result['chi2_after']:.1f}; report in {arguments.out}"
        )
    else:
        print(f"no mismatch found (chi2 {result['chi2_before']:.1f}); report in {arguments.out}")
    if result.requirement_sentence:
        print(result.requirement_sentence)
    return 0
