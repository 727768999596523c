"""Rule-level tests of the simulation stages on a tiny configuration."""

import h5py
import numpy as np
import pytest
from helpers import make_workdir, snakemake

pytestmark = pytest.mark.slow


def read_maps(path):
    with h5py.File(path) as maps:
        return {name: maps[name][()] for name in maps}, dict(maps.attrs)


def test_pair_maps_are_reproducible_and_independent_of_job_order(repo, tmp_path):
    targets = [
        "results/maps/M1-140/seed0.h5",
        "results/maps/M1-140/seed1.h5",
        "results/maps/L1-040/seed0.h5",
    ]
    runs = {}
    for cores, order in (("1", "seed-first"), ("2", "reversed")):
        workdir = make_workdir(repo, tmp_path / order)
        ordered = targets if order == "seed-first" else targets[::-1]
        result = snakemake(
            workdir,
            *ordered,
            extra=("--configfile", str(repo / "tests/configs/tiny.yaml"), "--cores", cores),
        )
        assert result.returncode == 0, result.stderr[-3000:]
        runs[order] = workdir

    for target in targets:
        first, attrs = read_maps(runs["seed-first"] / target)
        second, _ = read_maps(runs["reversed"] / target)
        for name in first:
            np.testing.assert_array_equal(first[name], second[name], err_msg=f"{target}:{name}")
    seed0, attrs = read_maps(runs["seed-first"] / targets[0])
    seed1, _ = read_maps(runs["seed-first"] / targets[1])
    seen = seed0["nosys"][0] != -1.6375e30
    assert seen.sum() > 50
    assert not np.allclose(seed0["nosys"][:, seen], seed1["nosys"][:, seen])  # CMB and noise
    assert seed0["templates"].shape == (2, 3, 12 * 16**2)
    # the input CMB alone through the same pointing, filter and binning: a CMB-like map
    reference = seed0["cmb_reference"]
    assert reference.shape == (3, 12 * 16**2)
    assert 20e-6 < reference[0, seen].std() < 300e-6
    assert np.isfinite(reference[:, seen]).all()
    assert attrs["a2_k_cmb"] > 0 and attrs["units"] == "K_CMB"
    assert attrs["POLCCONV"] == "COSMO" and attrs["FWHM"] > 0 and attrs["FREQ"] == 140.0
    _, lft_attrs = read_maps(runs["seed-first"] / targets[2])
    assert lft_attrs["a2_k_cmb"] == 0.0  # LFT carries no HWPSS (paper: ideal)
    assert np.isfinite(seed0["condition"][seen]).all()


def test_map_domain_maps_have_the_tod_format_and_reproduce(repo, tmp_path, tiny_local_run):
    """simulation.realizations = map_domain: the fixed pass and the per-channel seed job
    write maps files with the TOD path's datasets, shapes and attributes, bit for bit the
    same when rerun (other job order, other core count), and different seeds differ."""
    import shutil

    tod_workdir, tod_result = tiny_local_run
    assert tod_result.returncode == 0, tod_result.stderr[-3000:]
    override = tmp_path / "map_domain.yaml"
    override.write_text("simulation:\n  realizations: map_domain\n")
    configs = ("--configfile", str(repo / "tests/configs/tiny.yaml"), str(override))
    targets = [
        "results/maps/M1-140/seed1.h5",
        "results/maps/M1-140/seed0.h5",
        "results/maps/L1-040/seed0.h5",
    ]
    workdir = make_workdir(repo, tmp_path / "run")
    for inputs in ("results/inputs", "results/sky"):  # the upstream stages, already run
        shutil.copytree(tod_workdir / inputs, workdir / inputs)
    result = snakemake(workdir, *targets, extra=(*configs, "--cores", "2"))
    assert result.returncode == 0, result.stderr[-3000:]
    first = {target: read_maps(workdir / target) for target in targets}
    # the M1-140 fixed pass and its seeds again, alone, on one core, seeds in reverse order
    shutil.rmtree(workdir / "results/maps/M1-140")
    result = snakemake(workdir, *targets[1::-1], extra=(*configs, "--cores", "1"))
    assert result.returncode == 0, result.stderr[-3000:]
    for target in targets:
        fast, fast_attrs = first[target]
        again, _ = read_maps(workdir / target)
        full, full_attrs = read_maps(tod_workdir / target)
        assert set(fast) == set(full), target
        for name in full:
            assert fast[name].shape == full[name].shape, (target, name)
            np.testing.assert_array_equal(fast[name], again[name], err_msg=f"{target}:{name}")
        assert set(full_attrs) <= set(fast_attrs)
        assert fast_attrs["realization"] == "map_domain"
    seed1, seed0 = first[targets[0]][0], first[targets[1]][0]
    seen = seed0["nosys"][0] != -1.6375e30
    assert not np.allclose(seed0["nosys"][:, seen], seed1["nosys"][:, seen])
    # the TOD path's CMB realization of the same seed, through the filter's transfer
    full0, _ = read_maps(tod_workdir / targets[1])
    correlation = np.corrcoef(seed0["cmb_reference"][0, seen], full0["cmb_reference"][0, seen])
    assert correlation[0, 1] > 0.5
