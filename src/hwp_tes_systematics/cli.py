"""Command line: ``python -m hwp_tes_systematics <command>``."""

from __future__ import annotations

import argparse
import sys

from .config import config_reference_markdown


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hwp_tes_systematics", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("config-reference", help="print the configuration reference (Markdown)")
    arguments = parser.parse_args(argv)
    if arguments.command == "config-reference":
        sys.stdout.write(config_reference_markdown())
    return 0
