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
from helpers import TINY_DEFAULT, make_workdir, snakemake, tiny_configfiles

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


def _once_per_run(tmp_path_factory, name: str, run) -> tuple:
    """``run(workdir)`` (returning a CompletedProcess) once per pytest run, shared by the
    xdist workers: the first to ask runs it holding a file lock in the directory they
    share, the others wait for it and read its outcome. (workdir, outcome with
    ``returncode`` and ``stderr``)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / name
    else:
        shared = tmp_path_factory.mktemp(name)
    shared.mkdir(exist_ok=True)
    workdir, outcome = shared / "workdir", shared / "outcome.json"
    with open(shared / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not outcome.exists():
            shutil.rmtree(workdir, ignore_errors=True)  # left by a worker that crashed
            result = run(workdir)
            outcome.write_text(
                json.dumps({"returncode": result.returncode, "stderr": result.stderr[-20000:]})
            )
        return workdir, SimpleNamespace(**json.loads(outcome.read_text()))


@pytest.fixture(scope="session")
def tiny_local_run(repo, tmp_path_factory):
    """The whole DAG on the tiny configuration (helpers.TINY_CONFIGS), local, 2 cores:
    (workdir, result with ``returncode`` and ``stderr``), once per pytest run (shared by
    the end-to-end tests and the SLURM comparison)."""

    def run(workdir):
        make_workdir(repo, workdir)
        configs = tiny_configfiles(repo)
        return snakemake(workdir, extra=("--configfile", *configs, "--cores", "2"))

    return _once_per_run(tmp_path_factory, "tiny_local_run", run)


@pytest.fixture(scope="session")
def tiny_default_run(repo, tiny_local_run, tmp_path_factory):
    """The embedded default's path at tiny size (helpers.TINY_DEFAULT) in its
    own work folder, its inputs and sky copied from the tiny TOD run (the same upstream
    stages): (workdir, result), once per pytest run. Tests that change it work on a copy."""
    tod_workdir, tod_result = tiny_local_run

    def run(workdir):
        make_workdir(repo, workdir)
        if tod_result.returncode != 0:
            return SimpleNamespace(returncode=1, stderr="the tiny TOD run failed")
        for inputs in ("results/inputs", "results/sky"):
            shutil.copytree(tod_workdir / inputs, workdir / inputs)
        config = str(repo / TINY_DEFAULT)
        return snakemake(workdir, extra=("--configfile", config, "--cores", "2"))

    return _once_per_run(tmp_path_factory, "tiny_default_run", run)


# The test pyramid: each test gets one kind (its marker), from its file and tier.
#   unit      fast checks of one function or file format (pytest -m unit: seconds)
#   physics   a result against an analytic expectation or the reference path it replaces
#   rule      one Snakemake rule (or a few) on tiny inputs
#   workflow  a whole command: the DAG, a profile, the installed package, the docs build,
#             a benchmark, the command line on a recording
TEST_KINDS = ("unit", "physics", "rule", "workflow")
PHYSICS_FILES = {
    # instrument, sky
    "test_radiometry.py", "test_tes.py", "test_hwp_power.py", "test_nonlinearity_lines.py",
    "test_focal_plane.py", "test_sky.py",
    # simulation
    "test_baselines.py", "test_data_model.py", "test_demodulation.py",
    "test_fixed_pass_reference.py", "test_fixed_pass_variants.py", "test_map_domain.py",
    "test_map_domain_demodulated.py", "test_notch.py", "test_tod_maps.py",
    # analysis
    "test_hilc.py", "test_ilc_residuals.py", "test_likelihood.py", "test_model_consistency.py",
    "test_requirement.py", "test_spectra.py", "test_template_fit.py",
    "test_fixed_instruments.py",
    # diagnose
    "test_diagnose_clean.py", "test_diagnose_effects.py", "test_diagnose_fluctuations.py",
    "test_diagnose_gaps.py", "test_diagnose_linalg.py", "test_diagnose_noise.py",
    "test_diagnose_nominal.py", "test_diagnose_pairs.py", "test_diagnose_pointing.py",
    "test_diagnose_rolloff.py", "test_diagnose_segments.py", "test_diagnose_sky_sources.py",
    "test_effect_registry.py", "test_glitch_events.py", "test_readout_steps.py",
}  # fmt: skip
RULE_FILES = {"test_rules_inputs.py", "test_rules_maps.py"}
WORKFLOW_FILES = {"test_end_to_end.py", "test_profiles.py", "test_slurm.py", "test_install.py"}


def kind_of_test(path: Path, slow: bool) -> str:
    """The kind (TEST_KINDS) of a test in file ``path``, ``slow`` if marked so: by its
    file; a slow test elsewhere runs a whole command (workflow); unit tests are fast."""
    if path.name in RULE_FILES:
        return "rule"
    if path.name in WORKFLOW_FILES:
        return "workflow"
    if path.name in PHYSICS_FILES:
        return "physics"
    return "workflow" if slow else "unit"


# run first: a test that mostly waits (the SLURM run, a chain of one-CPU jobs), so that
# the other worker's tests fill its waits instead of following it
RUN_FIRST = ("test_slurm.py",)


@pytest.hookimpl(tryfirst=True)  # before -m selects on the markers
def pytest_collection_modifyitems(config, items):
    """Each test's kind marker (:func:`kind_of_test`); the order: RUN_FIRST, then the slow
    tests, then the fast ones (under xdist the short ones at the end even out the
    workers' ends), each group in file order."""
    for item in items:
        kind = kind_of_test(Path(str(item.path)), item.get_closest_marker("slow") is not None)
        item.add_marker(getattr(pytest.mark, kind))
    items[:] = sorted(
        items,
        key=lambda item: (
            Path(str(item.path)).name not in RUN_FIRST,
            item.get_closest_marker("slow") is None,
        ),
    )
