"""Command line: ``python -m hwp_tes_systematics <command>``.

config-reference                      print the configuration reference (Markdown)
effect-catalog                        print the diagnosis's effect catalog (Markdown)
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
):
    """Diagnose one recording with the nominal HWPSS and noise of the configured instrument.

    ``a2_k`` (``--a2``) overrides the instrument model's A_2; a channel the model does not
    know (a lab detector) needs it (see :func:`.diagnose.recording.nominal_a2`).
    ``requirement`` (``--requirement``): the requirement.json a found nonlinearity is
    compared with (default: the shipped one-year result).
    """
    from .diagnose import diagnose
    from .diagnose.recording import nominal_a2, read_recording
    from .simulation.channel_inputs import channel_a2_k_cmb

    config = load_config(*config_paths)
    recording = read_recording(recording_path)
    a2_k = nominal_a2(recording, a2_k, lambda channel: channel_a2_k_cmb(config, channel))
    log.info(
        "%s: channel %s, %d detectors, %.2f h; nominal A_2 = %.4g K_CMB",
        recording_path,
        recording.channel,
        recording.n_detectors,
        recording.n_samples / recording.sampling_rate_hz / 3600,
        a2_k,
    )
    return diagnose(
        recording,
        sky_path,
        a2_k,
        out_dir=out_dir,
        delta_bic_threshold=threshold,
        workers=workers,
        requirement=requirement,
    )


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
    arguments = parser.parse_args(argv)

    if arguments.command == "config-reference":
        sys.stdout.write(config_reference_markdown())
        return 0
    if arguments.command == "effect-catalog":
        from .diagnose.catalog import effect_catalog_markdown

        sys.stdout.write(effect_catalog_markdown())
        return 0

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
        )
    except (ConfigError, ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if result["mismatch_found"]:
        names = ", ".join(effect["name"] for effect in result["effects"])
        print(
            f"mismatch found: {names}; chi2 {result['chi2_before']:.1f} -> "
            f"{result['chi2_after']:.1f}; report in {arguments.out}"
        )
        if result.requirement_sentence:
            print(result.requirement_sentence)
    else:
        print(f"no mismatch found (chi2 {result['chi2_before']:.1f}); report in {arguments.out}")
    return 0
