"""Rule-level tests of the simulation stages on a tiny configuration."""

import h5py
import numpy as np
import pytest
from helpers import make_workdir, snakemake, tiny_configfiles

pytestmark = pytest.mark.slow


def read_maps(path):
    with h5py.File(path) as maps:
        return {name: maps[name][()] for name in maps}, dict(maps.attrs)


def test_pair_maps_are_reproducible_and_independent_of_job_order(repo, tmp_path, tiny_local_run):
    """The tiny run's pair maps (the whole DAG, 2 cores, Snakemake's order) and the same
    maps made alone on 1 core, targets in reverse order: bit for bit the same."""
    tod_workdir, tod_result = tiny_local_run
    assert tod_result.returncode == 0, tod_result.stderr[-3000:]
    targets = [
        "results/maps/M1-140/seed0.h5",
        "results/maps/M1-140/seed1.h5",
        "results/maps/L1-040/seed0.h5",
    ]
    workdir = make_workdir(repo, tmp_path / "reversed")
    result = snakemake(
        workdir, *targets[::-1], extra=("--configfile", *tiny_configfiles(repo), "--cores", "1")
    )
    assert result.returncode == 0, result.stderr[-3000:]
    runs = {"seed-first": tod_workdir, "reversed": workdir}

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


def test_map_domain_alms_reproduce_and_equal_the_maps_path(repo, tmp_path, tiny_local_run):
    """simulation.realizations = map_domain: the fixed pass, the analysis mask and the
    per-channel seed job write each seed's a_lm, bit for bit the same when rerun (other job
    order, other core count), different between seeds; the HILC of seed 0 from them
    equals, to round-off, the HILC of the same seed's maps written to files (the path the
    seeds' maps took before they were kept in memory)."""
    import shutil

    import pandas as pd

    from hwp_tes_systematics.analysis.ilc_residuals import SeedMaps
    from hwp_tes_systematics.config import deep_merge, load_config
    from hwp_tes_systematics.simulation.map_domain import ChannelSeeds
    from hwp_tes_systematics.simulation.maps_file import write_channel_maps

    tod_workdir, tod_result = tiny_local_run
    assert tod_result.returncode == 0, tod_result.stderr[-3000:]
    override = tmp_path / "map_domain.yaml"
    override.write_text("simulation:\n  realizations: map_domain\n")
    configs = ("--configfile", *tiny_configfiles(repo), str(override))
    targets = [
        "results/alms/M1-140/seed1.h5",
        "results/alms/M1-140/seed0.h5",
        "results/alms/L1-040/seed0.h5",
        "results/spectra/seed0/nosys.csv",
    ]
    workdir = make_workdir(repo, tmp_path / "run")
    for inputs in ("results/inputs", "results/sky"):  # the upstream stages, already run
        shutil.copytree(tod_workdir / inputs, workdir / inputs)
    result = snakemake(workdir, *targets, extra=(*configs, "--cores", "2"))
    assert result.returncode == 0, result.stderr[-3000:]
    alm_files = targets[:3]
    first = {target: read_maps(workdir / target) for target in alm_files}
    # the M1-140 fixed pass and its seeds again, alone, on one core
    shutil.rmtree(workdir / "results/maps/M1-140")
    shutil.rmtree(workdir / "results/alms/M1-140")
    result = snakemake(workdir, *alm_files[1::-1], extra=(*configs, "--cores", "1"))
    assert result.returncode == 0, result.stderr[-3000:]
    for target in alm_files:
        again, _ = read_maps(workdir / target)
        for name, values in first[target][0].items():
            np.testing.assert_array_equal(values, again[name], err_msg=f"{target}:{name}")
    seed1, seed0 = first[alm_files[0]][0], first[alm_files[1]][0]
    assert not np.allclose(seed0["alm_nosys"], seed1["alm_nosys"])
    np.testing.assert_array_equal(
        seed0["alm_foreground_reference"], seed1["alm_foreground_reference"]
    )
    # one template a_lm per detector and the seed's two pieces of the s h term, so the
    # component separation gives fixed instruments and the template's split
    assert seed0["alm_x1"].shape[0] == seed0["alm_x1_noise_h"].shape[0] == 2
    systematic = pd.read_csv(workdir / "results/spectra/seed0/systematic_only.csv")
    assert np.all(systematic["bb_noise_h_x_noise_h_k4"][2:] > 0)
    instruments = pd.read_csv(workdir / "results/spectra/seed0/fixed_instruments.csv")
    assert "bb_cross_instrument19_k3" in instruments

    # the same seed through maps files: the HILC's residual spectra agree to round-off
    config = deep_merge(
        load_config(repo / "config/config.yaml", *tiny_configfiles(repo)),
        {"simulation": {"realizations": "map_domain"}},
    )
    map_paths = {}
    for name in ("L1-040", "M1-140"):
        fixed_h5 = workdir / f"results/maps/{name}/fixed_pass_nside16_baselines60s.h5"
        maps = ChannelSeeds(config, fixed_h5).maps(0)
        fixed = read_maps(fixed_h5)[0]
        map_paths[name] = str(tmp_path / f"{name}_seed0.h5")
        write_channel_maps(map_paths[name], maps, fixed["hits"], fixed["condition"], maps["attrs"])
    from_maps = SeedMaps.load(config, 0, map_paths).residual_spectra(0.1)
    from_alms = SeedMaps.from_alm_files(
        config,
        0,
        {name: str(workdir / f"results/alms/{name}/seed0.h5") for name in map_paths},
        str(workdir / "results/alms/analysis_mask.h5"),
    ).residual_spectra(0.1)
    for column in ("bb_residual_k2", "bb_noise_residual_k2", "bb_cmb_input_k2"):
        np.testing.assert_allclose(from_alms[column], from_maps[column], rtol=1e-9, atol=0)
    # the template fit on the map-domain path knows the fixed pass's templates only: it
    # leaves the seed's own part of the s h term less its projection, W-orthogonal to them
    fitted = SeedMaps.from_alm_files(
        {**config, "mitigation": {"template_fit": "detector"}},
        0,
        {name: str(workdir / f"results/alms/{name}/seed0.h5") for name in map_paths},
        str(workdir / "results/alms/analysis_mask.h5"),
    )
    (report,) = fitted.template_fits
    assert report["channel"] == "M1-140" and report["templates_known"].startswith("the fixed")
    m1 = fitted.names.index("M1-140")
    left = fitted.channel_alms["fit_residual"][m1]
    pieces = sum(fitted.channel_alms[kind][m1] for kind in ("x1_cmb_h", "x1_noise_h"))
    assert np.abs(left).max() > 0 and np.abs(pieces).max() > 0
    injected = np.array(report["injected_unit_draw"])
    missed = np.abs(np.array(report["fitted_unit_response"]) - injected)
    assert missed.max() < 0.5 * np.abs(injected).max(), (missed, injected)  # known part dominates
    written = pd.read_csv(workdir / "results/spectra/seed0/nosys.csv")
    nosys_from_maps = SeedMaps.load(config, 0, map_paths).residual_spectra(0.0)
    np.testing.assert_allclose(
        written["bb_residual_k2"], nosys_from_maps["bb_residual_k2"], rtol=1e-9, atol=0
    )
    # the seed's tensor probe, put in at r = 1 and recovered: its power over C_GW is about
    # 1 on the mask as put in (cosmic variance of one seed) and less after the filters
    from hwp_tes_systematics.analysis.noise_model import tensor_response_columns

    response = tensor_response_columns([written])
    ell = slice(8, 33)
    put_in = np.median(response["tensor_input_over_theory_bb"][ell])
    assert 0.5 < put_in < 2.0, put_in
    assert np.median(response["tensor_response_bb"][ell]) < put_in
    # the TOD path's CMB realization of the same seed, through the filter's transfer
    maps0 = read_maps(map_paths["M1-140"])[0]
    full0, _ = read_maps(tod_workdir / "results/maps/M1-140/seed0.h5")
    seen = maps0["nosys"][0] != -1.6375e30
    correlation = np.corrcoef(maps0["cmb_reference"][0, seen], full0["cmb_reference"][0, seen])
    assert correlation[0, 1] > 0.5


def test_a_demodulated_analysis_runs_from_its_own_fixed_pass_file(repo, tmp_path, tiny_local_run):
    """config/demodulated.yaml on the tiny map-domain run: one fixed pass per channel
    writes the binned and the demodulated map-makers' files (the latter pointing to the
    former for the HWPSS moments, with its own measured T^h of the s h term's CMB part),
    and the seeds' a_lm and spectra are made from the demodulated one."""
    import shutil

    import h5py

    tod_workdir, tod_result = tiny_local_run
    assert tod_result.returncode == 0, tod_result.stderr[-3000:]
    override = tmp_path / "map_domain.yaml"
    override.write_text("simulation:\n  realizations: map_domain\n")
    configs = (
        "--configfile",
        *tiny_configfiles(repo),
        str(override),
        str(repo / "config/demodulated.yaml"),
    )
    workdir = make_workdir(repo, tmp_path / "run")
    for inputs in ("results/inputs", "results/sky"):  # the upstream stages, already run
        shutil.copytree(tod_workdir / inputs, workdir / inputs)
    target = "results/spectra/seed0/nosys.csv"
    result = snakemake(workdir, target, extra=(*configs, "--cores", "2"))
    assert result.returncode == 0, result.stderr[-3000:]
    maps = workdir / "results/maps/M1-140"
    with h5py.File(maps / "fixed_pass_nside16_baselines60s_demodulated.h5") as demodulated:
        assert demodulated.attrs["map_maker"] == "demodulated"
        assert demodulated.attrs["sky_scanning"] == "band_limited"
        assert demodulated.attrs["moments_in"] == "fixed_pass_nside16_baselines60s.h5"
        transfer = demodulated["cmb_h_transfer"][()]
    with h5py.File(maps / "fixed_pass_nside16_baselines60s.h5") as binned:
        assert binned.attrs["map_maker"] == "binned" and binned["cmb_h_transfer"].size == 0
    assert transfer.shape[0] == 3 and np.abs(transfer[:, 2:]).max() < 1e-3
    assert (workdir / target).exists()
