"""Set-up shared by the benchmarks: one PTEP detector pair simulated like a pair_maps job."""

from __future__ import annotations

import resource
import time

import numpy as np

from hwp_tes_systematics import sky
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.io import use_threads
from hwp_tes_systematics.simulation import fixed_maps
from hwp_tes_systematics.simulation.channel_inputs import channel_a2_k_cmb, channel_sky
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import PairMapSettings, accumulate
from hwp_tes_systematics.sky import cmb as sky_cmb
from hwp_tes_systematics.timing import StageClock

MASTER_SEED, SEED = 1, 0
START_TDB = "2032-04-01T00:00:00"
A2_K_CMB = 0.264  # M1-140 HWPSS amplitude of the default config (results/inputs/kw_conversion.csv)


def paper_settings(plan, nside, a2_k_cmb, **changes) -> PairMapSettings:
    """PairMapSettings with config/config.yaml's notch (width 4 f_HWP / 100, 1200 s
    margins) and condition limit, master seed MASTER_SEED, seed SEED; ``changes`` override."""
    values = {
        "master_seed": MASTER_SEED,
        "seed": SEED,
        "nside": nside,
        "plan": plan,
        "a2_k_cmb": a2_k_cmb,
        "notch_width_divisor": 100.0,
        "notch_margin_s": 1200.0,
        "max_condition_number": 100.0,
    }
    return PairMapSettings(**(values | changes))


def pair_setup(
    channel_name="M1-140",
    duration_s=86400.0,
    nside=64,
    threads=1,
    noise_model="keshner",
    chunk_s=86400.0,
    noise_scale=1.0,
):
    """(simulator, settings, sky map) of one (channel, seed) job; the sky is a CMB map.
    All kernels use ``threads`` threads (as a pair_maps job with Snakemake's threads)."""
    use_threads(threads)
    channel = load_channel(channel_name)
    plan = MissionPlan(START_TDB, duration_s, min(chunk_s, duration_s), channel.sampling_rate_hz)
    settings = paper_settings(plan, nside, A2_K_CMB, noise_scale=noise_scale, threads=threads)
    simulator = PairSimulator(channel, plan, nside, threads=threads, noise_model=noise_model)
    sky_map = sky.cmb_map(nside, 3 * nside - 1, 0.0, MASTER_SEED, SEED, channel.fwhm_arcmin)
    return simulator, settings, sky_map


def fixed_pass_setup(channel_name, days, nside, rate_hz, a2_k_cmb, baseline_length_s, seed=1):
    """(simulator, settings) of a map-domain fixed pass of ``days`` of one pair at
    ``rate_hz``, the sky scanned at ``nside`` (:func:`paper_settings`, master seed
    ``seed``)."""
    channel = load_channel(channel_name)
    plan = MissionPlan(START_TDB, days * 86400.0, 86400.0, rate_hz)
    settings = paper_settings(
        plan,
        nside,
        a2_k_cmb,
        master_seed=seed,
        seed=fixed_maps.NOISE_REFERENCE_SEED,
        baseline_length_s=baseline_length_s,
    )
    return PairSimulator(channel, plan, nside, noise_model="keshner"), settings


def config_fixed_pass(config, channel_name, days, rate_hz, nside, **options):
    """A map-domain fixed pass of ``days`` of one pair of ``channel_name`` at ``rate_hz``
    with ``config``'s filter, its sky scanned at ``nside`` with unit noise:
    (FixedMaps, A_2 [K_CMB], channel, wall seconds); ``options`` go to
    :func:`fixed_maps.fixed_pass`."""
    lmax = 3 * nside - 1
    channel = load_channel(channel_name)
    plan = MissionPlan(config["simulation"]["mission_start_tdb"], days * 86400.0, 86400.0, rate_hz)
    a2_k = channel_a2_k_cmb(config, channel_name)
    settings = PairMapSettings.from_config(
        config,
        channel,
        fixed_maps.NOISE_REFERENCE_SEED,
        a2_k,
        plan=plan,
        nside=nside,
        noise_scale=1.0,
    )
    simulator = PairSimulator(channel, plan, nside, noise_model="keshner")
    sky_config = {**config, "maps": {**config["maps"], "nside": nside}}
    foreground = channel_sky(sky_config, channel, 0)["foreground"]
    transfer_alm = sky_cmb.transfer_cmb_alm(lmax, 0.0, config["master_seed"], channel.fwhm_arcmin)
    started = time.perf_counter()
    fixed = fixed_maps.fixed_pass(
        simulator, settings, foreground, transfer_alm, True, lmax, **options
    )
    return fixed, a2_k, channel, time.perf_counter() - started


def warm_up(channel_name, nside, threads, noise_model):
    """Compile the numba kernels and load litebird_sim's caches on a 10-minute run."""
    simulator, settings, sky_map = pair_setup(channel_name, 600.0, nside, threads, noise_model)
    accumulate(simulator, settings, sky_map, references_iqu_k=(sky_map, sky_map))
    accumulate(simulator, settings, sky_map, g1_per_k=np.zeros(simulator.n_detectors))


def timed_accumulate(simulator, settings, sky_map, path: str, on_chunk=None):
    """Run one path; returns (equations, wall seconds, StageClock).

    plain: one TOD d (the cost of one sigma_g1 case simulated directly);
    linear: d and the per-detector template terms s^2, s h, h^2 of d_k^2 (every sigma_g1
    and every HWPSS amplitude at once);
    job: linear plus the CMB and foreground reference TODs, what a pair_maps job does
    (the second reference is a CMB map here; its cost is the same).
    """
    clock = StageClock()
    started = time.perf_counter()
    if path == "plain":
        g1, references = np.zeros(simulator.n_detectors), ()
    elif path == "linear":
        g1, references = None, ()
    elif path == "job":
        g1, references = None, (sky_map, sky_map)
    else:
        raise ValueError(f"path {path!r}: expected plain, linear or job")
    equations = accumulate(
        simulator,
        settings,
        sky_map,
        g1_per_k=g1,
        on_chunk=on_chunk,
        references_iqu_k=references,
        clock=clock,
    )
    return equations, time.perf_counter() - started, clock


def peak_rss_mb() -> float:
    """Peak resident memory of this process [MB]."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_fixed_pass(
    name,
    carries_systematics,
    nside,
    rate_hz,
    days,
    calibration_every=1,
    measure_lmax=None,
    extra_variants=(),
    demodulated=False,
    band_limited=False,
    noise_realizations=1,
):
    """(seconds, {variant: FixedMaps}, simulator) of the map-domain fixed pass of ``days``
    of channel ``name`` (:func:`fixed_pass_setup`, 60 s baselines, no foreground, the
    reference CMB of master seed 1): T_ell and S_ell measured up to ``measure_lmax``
    (None: the full band); ``extra_variants``: (nside, baseline length) map-makers binned
    in the same pass, ``nside`` the scan's; ``demodulated``: each binned one also
    demodulated; ``band_limited``: the sky scanned from its a_lm; ``noise_realizations``:
    the reference noise realizations (simulation.noise_reference_realizations)."""
    import healpy as hp

    channel = load_channel(name)
    a2_k_cmb = A2_K_CMB if carries_systematics else 0.0
    simulator, settings = fixed_pass_setup(name, days, nside, rate_hz, a2_k_cmb, 60.0)
    lmax = 3 * nside - 1
    foreground = np.zeros((3, hp.nside2npix(nside)))
    alm = sky_cmb.transfer_cmb_alm(lmax, 0.0, 1, channel.fwhm_arcmin)
    binned = [(nside, settings.baseline_length_s), *extra_variants]
    started = time.perf_counter()
    passes = fixed_maps.fixed_passes(
        simulator,
        settings,
        foreground,
        alm,
        carries_systematics,
        lmax,
        calibration_every,
        measure_lmax=measure_lmax,
        extra_variants=extra_variants,
        demodulated_variants=binned if demodulated else (),
        band_limited_sky=band_limited,
        noise_realizations=noise_realizations,
    )
    return time.perf_counter() - started, passes, simulator
