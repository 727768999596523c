"""Side by side: the naive litebird_sim path against the workflow's linear-in-g1 path.

    python benchmarks/naive_vs_workflow.py --channel M1-140 --hours 24 --nside 64

(a) naive: for the no-systematics case and each sigma_g1, a full simulation with
    litebird_sim's documented calls: pointing (prepare/precompute_pointings),
    scan_map_in_observations, add_dipole_to_observations, add_noise_to_observations,
    add_2f, apply_quadratic_nonlin_for_one_detector, then the HWPSS 2f removal and the
    notch, and make_binned_map;
(b) workflow: one simulation giving m_nosys and the per-detector templates T_k, and
    m(sigma) = m_nosys + sigma sum_k z_k T_k for every sigma.
Same inputs (sky, pointing, noise streams, g1 draws). Prints the time of each path,
ns per detector-sample, the ratio, and max |m_naive - m_workflow| / rms(m) per case.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from hwp_tes_systematics import seeding, sky
from hwp_tes_systematics.instrument import load_channel
from hwp_tes_systematics.mapmaking import solve_maps
from hwp_tes_systematics.notch import margin_samples
from hwp_tes_systematics.stages.pair_maps import PairMapSettings, accumulate, filter_tod
from hwp_tes_systematics.systematics import maps_for_sigma, unit_g1_draws
from hwp_tes_systematics.tod import MissionPlan, PairSimulator

MASTER_SEED, SEED = 1, 0


def naive_map(simulator, settings, sky_map, g1_per_k):
    """One case through litebird_sim's calls, one chunk (with filter margins)."""
    import litebird_sim as lbs
    from litebird_sim.hwp_diff_emiss import add_2f
    from litebird_sim.non_linearity import apply_quadratic_nonlin_for_one_detector

    plan = settings.plan
    margin = margin_samples(plan.sampling_rate_hz, settings.notch_margin_s)
    _, first, n_samples = plan.chunks()[0]
    pointing = simulator.pointing(first - margin, n_samples + 2 * margin)
    observation = pointing.observation
    observation.tod[:] = 0.0
    offset_s = (first - margin) / plan.sampling_rate_hz
    hwp = lbs.IdealHWP(
        simulator.hwp_rad_per_s,
        start_angle_rad=float(np.mod(simulator.hwp_rad_per_s * offset_s, 2 * np.pi)),
    )
    healpix_map = lbs.HealpixMap(
        values=sky_map, nside=settings.nside, coordinates=lbs.CoordinateSystem.Galactic
    )
    lbs.scan_map_in_observations(observation, maps=healpix_map, hwp=hwp)
    lbs.add_dipole_to_observations(observation, pos_and_vel=simulator.orbit)
    noise = [
        seeding.rng(settings.master_seed, "noise", simulator.channel.name, settings.seed, 0, name)
        for name in simulator.detector_names
    ]
    lbs.add_noise_to_observations(
        observation, "one_over_f", dets_random=noise, scale=settings.noise_scale
    )
    add_2f(
        observation.tod,
        pointing.hwp_angle_rad,
        simulator.pol_angles_rad,
        np.full(simulator.n_detectors, settings.a2_k_cmb),
    )
    for index, g1 in enumerate(g1_per_k):
        apply_quadratic_nonlin_for_one_detector(
            observation.tod[index],
            nl_params=lbs.NonLinParams(
                sampling_gaussian_loc=float(g1), sampling_gaussian_scale=0.0
            ),
            random=np.random.default_rng(0),
        )
    inner = slice(margin, margin + n_samples)
    filtered = filter_tod(observation.tod.copy(), pointing, inner, simulator, settings)
    inner_pointing = simulator.pointing(first, n_samples)
    inner_pointing.observation.tod[:] = filtered
    offset_s = first / plan.sampling_rate_hz
    hwp_inner = lbs.IdealHWP(
        simulator.hwp_rad_per_s,
        start_angle_rad=float(np.mod(simulator.hwp_rad_per_s * offset_s, 2 * np.pi)),
    )
    result = lbs.make_binned_map(settings.nside, inner_pointing.observation, hwp=hwp_inner)
    return result.binned_map


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--hours", type=float, default=24.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--sigmas", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2, 1e-1])
    arguments = parser.parse_args()

    channel = load_channel(arguments.channel)
    duration_s = arguments.hours * 3600.0
    plan = MissionPlan("2032-04-01T00:00:00", duration_s, duration_s, channel.sampling_rate_hz)
    settings = PairMapSettings(
        master_seed=MASTER_SEED,
        seed=SEED,
        nside=arguments.nside,
        plan=plan,
        a2_k_cmb=0.264,
        notch_width_divisor=100.0,
        notch_margin_s=1200.0,
        max_condition_number=100.0,
    )
    simulator = PairSimulator(channel, plan, arguments.nside)
    sky_map = sky.cmb_map(
        arguments.nside, 3 * arguments.nside - 1, 0.0, MASTER_SEED, SEED, channel.fwhm_arcmin
    )
    draws = unit_g1_draws(MASTER_SEED, channel.name, SEED, simulator.detector_names)
    warm_plan = MissionPlan(plan.start_time_tdb, 600.0, 600.0, channel.sampling_rate_hz)
    warm = PairSimulator(channel, warm_plan, arguments.nside)
    warm_settings = PairMapSettings(**{**settings.__dict__, "plan": warm_plan})
    naive_map(warm, warm_settings, sky_map, np.zeros(2))
    accumulate(warm, warm_settings, sky_map)

    samples = plan.n_samples * simulator.n_detectors
    cases = [0.0, *arguments.sigmas]
    started = time.perf_counter()
    naive = {sigma: naive_map(simulator, settings, sky_map, sigma * draws) for sigma in cases}
    naive_s = time.perf_counter() - started

    started = time.perf_counter()
    maps, _, good = solve_maps(accumulate(simulator, settings, sky_map), 100.0)
    workflow = {sigma: maps_for_sigma(maps[0], maps[1:], draws, sigma) for sigma in cases}
    workflow_s = time.perf_counter() - started

    print(
        f"{channel.name}: {arguments.hours:g} h, {samples:.3e} detector-samples, "
        f"nside {arguments.nside}, cases: nosys + sigma_g1 {arguments.sigmas}"
    )
    print(
        f"naive    ({len(cases)} simulations): {naive_s:8.1f} s, "
        f"{1e9 * naive_s / samples:7.0f} ns per detector-sample"
    )
    print(
        f"workflow (1 simulation)    : {workflow_s:8.1f} s, "
        f"{1e9 * workflow_s / samples:7.0f} ns per detector-sample"
    )
    print(f"ratio naive / workflow = {naive_s / workflow_s:.1f} (target >= 10)")
    for sigma in cases:
        seen = good & (naive[sigma][0] != -1.6375e30)
        difference = np.abs(naive[sigma][:, seen] - workflow[sigma][:, seen]).max()
        rms = np.sqrt(np.mean(workflow[sigma][:, seen] ** 2))
        print(f"  sigma_g1 = {sigma:7.1e}: max |naive - workflow| / rms = {difference / rms:.2e}")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
