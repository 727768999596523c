"""Command line: ``hwp-tes-systematics <command>`` (the installed console script) or
``python -m hwp_tes_systematics <command>``.

config-reference                      print the configuration reference (Markdown)
effect-catalog                        print the diagnosis's effect catalog (Markdown)
figure8 REQUIREMENT.json --out PNG    redraw Fig. 8 from a run's requirement.json and
                                      the delta_r.csv beside it
diagnose RECORDING.h5 --sky SKY.fits [--config FILE] --out DIR
                                      locate, name, fit and report what the
                                      simulation left out of a recording

Works from any folder: the embedded default configuration (the repository's
config/config.yaml) and its HWP curve tables ship with the package; each
--config FILE is merged over it. Arguments and output paths are checked before any
work: a bad one stops at once (exit status 2) with an error naming the option.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
from pathlib import Path

from . import __version__
from .config import ConfigError, config_reference_markdown, default_config_path, load_config

log = logging.getLogger("hwp_tes_systematics")
MODULE_PROG = "python -m hwp_tes_systematics"

DIAGNOSE_DESCRIPTION = """\
Diagnose one recording against its simulation: build the nominal model (sky, dipole,
HWPSS A_2 cos 2(chi - theta)) from the recording's own pointing, HWP angle and detector
metadata, fit the nominal adjustments, locate where the residual differs from noise,
select and fit the effects of the catalog that explain it (BIC), and report what is
left unexplained. A nonlinearity found (or bounded) is compared with the requirement on
sigma_g1. A recording too long for the memory is diagnosed in segments.

Progress (stages, segments, elapsed time) goes to stderr: -q for warnings only, -v for
detail."""

DIAGNOSE_EPILOG = """\
writes, in --out DIR:
  diagnosis.json         the machine-readable diagnosis (effects, parameters, chi2, BIC,
                         nominal adjustments, unexplained structure, requirement check)
  diagnosis.md           the report, in Markdown
  residual_*.png         residual spectrum, versus HWP angle, time series and map, before
                         and after the fit
  segments/<i>/          each segment's own report, when diagnosed in segments
and prints one line (mismatch found or not, chi2 before -> after) and the sentence
comparing g1 with the requirement.

example:
  {prog} diagnose recording.h5 --sky sky.fits --out diagnosis/
  {prog} diagnose lab.h5 --sky sky.fits --a2 0.264 --segment-hours 6 --out lab/

exit status: 0 diagnosed; 2 bad arguments or input (the message names the option or the
file and what was expected)."""


def run_diagnose(
    recording_path: str | list[str],
    sky_path: str,
    config_paths: list[str],
    out_dir: str,
    threshold: float,
    workers: int = 1,
    a2_k: float | None = None,
    requirement: str | None = None,
    memory_gb: float | None = None,
    segment_hours: float | None = None,
    config: dict | None = None,
):
    """Diagnose one recording (a file, or the files of one observation's detectors) with
    the nominal HWPSS and noise of the configured instrument (``config``: the
    configuration already loaded from ``config_paths``, if it was).

    ``a2_k`` (``--a2``) overrides the instrument model's A_2; a channel the model does not
    know (a lab detector) needs it (see :func:`.diagnose.recording.nominal_a2`).
    ``requirement`` (``--requirement``): the requirement.json a found nonlinearity is
    compared with (default: the shipped one-year result). A recording whose diagnosis
    would not fit ``memory_gb`` (default: the available memory), or any recording with
    ``segment_hours``, is diagnosed in segments (:mod:`.diagnose.segments`).
    """
    from .diagnose import diagnose
    from .diagnose.recording import nominal_a2, read_recording
    from .diagnose.recording_checks import MIN_SAMPLES, recording_size
    from .diagnose.segments import diagnose_segments, needs_segments
    from .io import reuse_freed_memory, use_base_pages
    from .simulation.channel_inputs import channel_a2_k_cmb

    reuse_freed_memory()  # the fits' spectra of a row each: no page faults (io.reuse_freed_memory)
    use_base_pages()  # the first touch of ~10 GB without compaction stalls (io.use_base_pages)
    config = load_config(*config_paths) if config is None else config
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
        head.source,
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


def _number(name: str, accept, expected: str):
    """An argparse type: a float for which ``accept(value)`` holds, else an error naming
    the option (``name``) and what was expected."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and accept(value)):
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
        return value

    parse.__name__ = name  # argparse names the type in some messages
    return parse


def _existing_file(text: str) -> str:
    if not Path(text).is_file():
        what = "a folder" if Path(text).is_dir() else "no such file"
        raise argparse.ArgumentTypeError(f"{text}: {what} (expected a file)")
    return text


def _probe_writable(folder: Path) -> None:
    """Create and remove a file in ``folder`` (permissions, read-only file systems and
    quotas as they really are, for root too); OSError if that fails."""
    with tempfile.TemporaryFile(dir=folder):
        pass


def check_output(path: str, option: str, is_folder: bool) -> str | None:
    """None if ``path`` can be written (a folder created if missing, or a file), else a
    message naming ``option``, the path and what was expected. Nothing is created."""
    target = Path(path)
    if is_folder and target.exists() and not target.is_dir():
        return f"argument {option}: {path} exists and is not a folder (expected an output folder)"
    if not is_folder and target.is_dir():
        return f"argument {option}: {path} is a folder (expected the file to write)"
    folder = target if is_folder and target.is_dir() else target.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        return (
            f"argument {option}: {path} cannot be created: {folder} is a file, not a folder "
            "(expected a path in a writable folder)"
        )
    try:
        _probe_writable(folder)
    except OSError as error:
        return (
            f"argument {option}: {path} cannot be written: {folder} is not writable "
            f"({error.strerror or error}); expected a path in a writable folder"
        )
    return None


def check_sky_file(path: str) -> str | None:
    """None if ``path`` looks like a HEALPix I, Q, U FITS map (a binary table of at least
    three columns, read from its headers alone), else a message naming ``--sky``; the map
    itself is read and checked by the diagnosis (:func:`.diagnose.model.load_sky`)."""
    from astropy.io import fits

    try:
        with fits.open(path, memmap=True, lazy_load_hdus=False) as hdus:
            tables = [h for h in hdus if isinstance(h, fits.BinTableHDU)]
            columns = [len(h.columns) for h in tables]
    except (OSError, ValueError, TypeError) as error:
        return f"argument --sky: {path}: not a FITS file ({error}); expected a HEALPix I, Q, U map"
    if not any(n >= 3 for n in columns):
        return (
            f"argument --sky: {path}: FITS without a table of 3 columns (tables: {columns}); "
            "expected a HEALPix I, Q, U map in K_CMB (Galactic, RING)"
        )
    return None


def redraw_figure8(requirement_json: str, delta_r_csv: str | None, out_png: str) -> int:
    """Fig. 8 from a run's requirement.json and delta r table; 2 with a message naming the
    file when one is missing or is not what the requirement stage writes."""
    import json
    from pathlib import Path

    import pandas as pd

    from .analysis.requirement import figure8_arguments
    from .figures.results import plot_requirement

    requirement_path = Path(requirement_json)
    table_path = (
        requirement_path.with_name("delta_r.csv") if delta_r_csv is None else Path(delta_r_csv)
    )
    try:
        output = json.loads(requirement_path.read_text())
        table = pd.read_csv(table_path)
        written = plot_requirement(path=out_png, **figure8_arguments(output, table))
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


def program_name(argv0: str | None = None) -> str:
    """The name the command was run by: the console script's (``hwp-tes-systematics``),
    or ``python -m hwp_tes_systematics`` when run as a module."""
    name = Path(sys.argv[0] if argv0 is None else argv0).name
    return MODULE_PROG if name in ("__main__.py", "-c", "-m", "") else name


def build_parser(prog: str) -> tuple[argparse.ArgumentParser, dict]:
    """The command line's parser, its help naming the program ``prog``, and the parsers
    of its commands by name (their ``error`` names the command)."""
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog=prog,
        description=__doc__.split("\n\n", 1)[1],  # the commands, without the module's name
        epilog=f"example:\n  {prog} diagnose recording.h5 --sky sky.fits --out diagnosis/\n"
        f"  {prog} diagnose --help      (each command's own help)",
        formatter_class=formatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser(
        "config-reference",
        help="print the configuration reference (Markdown)",
        description="Print the configuration reference (Markdown) to stdout: every key of "
        "the schema with its type, default, unit and source (docs/workflow/configuration.md "
        "is this output).",
        epilog=f"example:\n  {prog} config-reference > configuration.md",
        formatter_class=formatter,
    )
    commands.add_parser(
        "effect-catalog",
        help="print the diagnosis's effect catalog (Markdown), from the code",
        description="Print the diagnosis's effect catalog (Markdown) to stdout, generated "
        "from the effect classes: each effect's model, parameters and signature.",
        epilog=f"example:\n  {prog} effect-catalog > effects.md",
        formatter_class=formatter,
    )
    figure8 = commands.add_parser(
        "figure8",
        help="redraw Fig. 8 (delta r versus sigma_g1) from a run's requirement.json and the "
        "delta_r.csv beside it (e.g. a committed run under docs/)",
        description="Redraw Fig. 8 (delta r versus sigma_g1, the requirement marked) from a "
        "workflow run's requirement.json and the delta_r.csv beside it; writes the PNG "
        "--out and prints its path.",
        epilog=f"example:\n  {prog} figure8 docs/one_year/requirement.json --out fig8.png",
        formatter_class=formatter,
    )
    figure8.add_argument(
        "requirement", type=_existing_file, help="a run's results/requirement.json"
    )
    figure8.add_argument(
        "--delta-r",
        default=None,
        type=_existing_file,
        help="its delta r table (default: delta_r.csv beside it)",
    )
    figure8.add_argument(
        "--out",
        required=True,
        help="the PNG to write (name ending in .png; missing folders are created)",
    )
    diagnose = commands.add_parser(
        "diagnose",
        help="find, name and fit what the simulation left out of a recording",
        description=DIAGNOSE_DESCRIPTION,
        epilog=DIAGNOSE_EPILOG.format(prog=prog),
        formatter_class=formatter,
    )
    diagnose.add_argument(
        "recording",
        type=_existing_file,
        nargs="+",
        help=(
            "litebird_sim or TOAST 3 HDF5 observation file; several: the detectors of one "
            "observation written apart (the same samples, start and HWP angle)"
        ),
    )
    diagnose.add_argument(
        "--sky",
        required=True,
        type=_existing_file,
        help="HEALPix I, Q, U FITS map, K_CMB, Galactic (RING)",
    )
    diagnose.add_argument(
        "--config",
        action="append",
        default=[],
        type=_existing_file,
        help="configuration file merged over the embedded default (config/config.yaml, "
        "shipped with the package); repeatable, later files win",
    )
    diagnose.add_argument(
        "--out", required=True, help="output folder (created if missing; checked first)"
    )
    diagnose.add_argument(
        "--delta-bic",
        type=_number("--delta-bic", lambda v: v <= 0, "a BIC change <= 0, e.g. -10"),
        default=-10.0,
        help="an effect is kept if it lowers the BIC by more (default -10)",
    )
    diagnose.add_argument(
        "--a2",
        type=_number("--a2", lambda v: v >= 0, "an amplitude >= 0 in K_CMB, e.g. 0.264"),
        default=None,
        help="nominal HWPSS amplitude A_2 [K_CMB]: overrides the instrument model's; needed "
        "for a channel not in it (a lab detector)",
    )
    diagnose.add_argument(
        "--requirement",
        default=None,
        type=_existing_file,
        help="a workflow run's results/requirement.json: a nonlinearity found is compared "
        "with its requirement on sigma_g1 (default: the shipped one-year result)",
    )
    diagnose.add_argument(
        "--memory-gb",
        type=_number("--memory-gb", lambda v: v > 0, "a memory > 0 GiB"),
        default=None,
        help="memory the diagnosis may use [GiB] (default: the available memory); a longer "
        "recording is diagnosed in segments that fit it",
    )
    diagnose.add_argument(
        "--segment-hours",
        type=_number("--segment-hours", lambda v: v > 0, "a duration > 0 h"),
        default=None,
        help="diagnose in segments of at most this many hours, combined in one report",
    )
    verbosity = diagnose.add_mutually_exclusive_group()
    verbosity.add_argument(
        "-q", "--quiet", action="store_true", help="no progress on stderr, warnings only"
    )
    verbosity.add_argument(
        "-v", "--verbose", action="store_true", help="detailed progress on stderr (debug)"
    )
    return parser, {"figure8": figure8, "diagnose": diagnose}


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run the command line on ``argv`` (default: sys.argv[1:]); the exit status."""
    parser, commands = build_parser(prog or program_name())
    arguments = parser.parse_args(argv)

    if arguments.command == "config-reference":
        sys.stdout.write(config_reference_markdown())
        return 0
    if arguments.command == "effect-catalog":
        from .diagnose.catalog import effect_catalog_markdown

        sys.stdout.write(effect_catalog_markdown())
        return 0
    if arguments.command == "figure8":
        problem = check_output(arguments.out, "--out", is_folder=False)
        if not problem and Path(arguments.out).suffix.lower() != ".png":
            problem = f"argument --out: {arguments.out}: expected a file name ending in .png"
        beside = Path(arguments.requirement).with_name("delta_r.csv")
        if not problem and arguments.delta_r is None and not beside.is_file():
            problem = (
                f"argument --delta-r: no {beside} beside the requirement file; give the "
                "run's delta_r.csv with --delta-r"
            )
        if problem:
            commands["figure8"].error(problem)
        return redraw_figure8(arguments.requirement, arguments.delta_r, arguments.out)

    problem = check_output(arguments.out, "--out", is_folder=True) or check_sky_file(arguments.sky)
    if problem:
        commands["diagnose"].error(problem)
    if arguments.requirement is not None:  # a bad one stops before the long diagnosis
        from .diagnose.bound.requirement_check import RequirementFileError, load_requirement

        try:
            load_requirement(arguments.requirement)
        except RequirementFileError as error:
            commands["diagnose"].error(f"argument --requirement: {error}")

    config_paths = [str(default_config_path()), *arguments.config]
    try:  # the configuration is an argument too: checked before the work
        config = load_config(*config_paths)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2

    from .io import setup_logging

    level = (
        logging.WARNING if arguments.quiet else logging.DEBUG if arguments.verbose else logging.INFO
    )
    setup_logging(level=level)
    # -v: every module's debug lines; otherwise the package's (set either way: an earlier
    # call in the same process may have left the package's logger at another level)
    log.setLevel(level)
    if not arguments.verbose:
        logging.getLogger().setLevel(logging.WARNING)
    try:
        result = run_diagnose(
            arguments.recording,
            arguments.sky,
            config_paths,
            arguments.out,
            arguments.delta_bic,
            a2_k=arguments.a2,
            requirement=arguments.requirement,
            memory_gb=arguments.memory_gb,
            segment_hours=arguments.segment_hours,
            config=config,
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
