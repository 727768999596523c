"""Helpers for the rule-level tests: a copy of the workflow in a temp dir, and a runner."""

import shutil
import subprocess
import sys


def make_workdir(repo, workdir):
    """A copy of the workflow (Snakefile, rules, scripts, config) in ``workdir``."""
    workdir.mkdir(parents=True, exist_ok=True)
    for item in ("Snakefile", "workflow", "config"):
        source = repo / item
        if source.is_dir():
            shutil.copytree(source, workdir / item)
        else:
            shutil.copy(source, workdir / item)
    return workdir


def snakemake(workdir, *targets, extra=()):
    """Run Snakemake (1 core unless ``extra`` says otherwise) and return the CompletedProcess."""
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", "--nolock", *extra, *targets],
        cwd=workdir,
        check=False,
        capture_output=True,
        text=True,
    )
