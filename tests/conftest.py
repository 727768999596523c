"""Shared fixtures: the repository root, the default configuration, the tiny run."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One BLAS thread per xdist worker (before numpy loads it): two workers with two
    # busy-waiting OpenBLAS threads each on two cores run several times slower.
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

import fcntl
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from helpers import make_workdir, snakemake

from hwp_tes_systematics.config import load_config

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "config.yaml"


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture
def default_config(monkeypatch) -> dict:
    """The embedded default configuration, read with the repository as working directory."""
    monkeypatch.chdir(REPO)
    return load_config(DEFAULT_CONFIG)


@pytest.fixture(scope="session")
def tiny_local_run(repo, tmp_path_factory):
    """The whole DAG on tests/configs/tiny.yaml, local, 2 cores: (workdir, result with
    ``returncode`` and ``stderr``).

    Run once per pytest run and shared by the end-to-end test and the SLURM comparison:
    under xdist the first worker to ask runs it (holding a file lock in the directory the
    workers share) and the others wait for it and read its outcome."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / "tiny_local_run"
    else:
        shared = tmp_path_factory.mktemp("tiny_local_run")
    shared.mkdir(exist_ok=True)
    workdir, outcome = shared / "workdir", shared / "outcome.json"
    with open(shared / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not outcome.exists():
            shutil.rmtree(workdir, ignore_errors=True)  # left by a worker that crashed
            make_workdir(repo, workdir)
            config = repo / "tests/configs/tiny.yaml"
            result = snakemake(workdir, extra=("--configfile", str(config), "--cores", "2"))
            outcome.write_text(
                json.dumps({"returncode": result.returncode, "stderr": result.stderr[-20000:]})
            )
        return workdir, SimpleNamespace(**json.loads(outcome.read_text()))
