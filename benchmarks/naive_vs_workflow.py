"""Side by side: the naive litebird_sim path against the workflow's linear-in-g1 path.

    python benchmarks/naive_vs_workflow.py --channel M1-140 --hours 24 --nside 64

Both paths simulate the same pair, sky, noise streams and g1 draws, one after the
other, each in its own process (so each has its own peak memory):

(a) naive: for the no-systematics case and each sigma_g1, a full simulation with
    litebird_sim's documented calls: prepare_pointings + precompute_pointings,
    scan_map_in_observations, add_dipole_to_observations, add_noise_to_observations,
    add_2f, apply_quadratic_nonlin_for_one_detector, then the 2f removal and the
    notch, and make_binned_map;
(b) workflow: one simulation giving m_nosys and the per-detector templates T_k
    (stages.pair_maps.accumulate), and m(sigma) = m_nosys + sigma sum_k z_k T_k.

Prints the time per stage, detector-samples per second and ns per detector-sample of
each path, its peak RSS, the ratio, and max |m_naive - m_workflow| / rms(m) per case.
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from types import SimpleNamespace

import astropy.time
import numpy as np
from common import MASTER_SEED, SEED, pair_setup, peak_rss_mb, timed_accumulate

from hwp_tes_systematics import seeding
from hwp_tes_systematics.analysis.systematics import maps_for_sigma, unit_g1_draws
from hwp_tes_systematics.instrument.channels import load_channel
from hwp_tes_systematics.simulation.hwpss_removal import harmonic_templates
from hwp_tes_systematics.simulation.mapmaking import solve_maps
from hwp_tes_systematics.simulation.notch import chunk_span
from hwp_tes_systematics.simulation.tod import NOISE_MODELS
from hwp_tes_systematics.simulation.tod_filter import filter_tod
from hwp_tes_systematics.simulation.tod_maps import split_solved_maps
from hwp_tes_systematics.timing import StageClock


def setup(arguments, duration_s):
    simulator, settings, sky_map = pair_setup(
        arguments.channel, duration_s, arguments.nside, arguments.threads, arguments.noise
    )
    draws = unit_g1_draws(MASTER_SEED, simulator.channel.name, SEED, simulator.detector_names)
    return simulator, settings, sky_map, draws


def naive_map(simulator, settings, sky_map, g1_per_k, clock):
    """One case through litebird_sim's calls (one chunk with the filter margins)."""
    import litebird_sim as lbs
    from litebird_sim.hwp_diff_emiss import add_2f
    from litebird_sim.non_linearity import apply_quadratic_nonlin_for_one_detector

    plan = settings.plan
    rate_hz = plan.sampling_rate_hz
    _, first, n_samples = plan.chunks()[0]
    start, n_simulated, inner = chunk_span(first, n_samples, rate_hz, settings.notch_margin_s)
    detectors = [d.__dict__ for d in simulator.detectors]

    def observation_and_hwp(first_sample, n):
        offset_s = first_sample / rate_hz
        start_time = plan.start_time + astropy.time.TimeDelta(offset_s, format="sec")
        observation = lbs.Observation(
            detectors=detectors,
            n_samples_global=n,
            start_time_global=start_time,
            sampling_rate_hz=rate_hz,
            tods=[lbs.TodDescription("tod", lbs.Units.K_CMB, np.float64, "total signal")],
        )
        hwp = lbs.IdealHWP(
            simulator.hwp_rad_per_s,
            start_angle_rad=float(np.mod(simulator.hwp_rad_per_s * offset_s, 2 * np.pi)),
        )
        return observation, hwp, start_time

    with clock("pointing"):
        observation, hwp, start_time = observation_and_hwp(start, n_simulated)
        quaternions = simulator.scanning.spin_to_ecliptic(start_time, n_simulated / rate_hz + 4)
        lbs.prepare_pointings(observation, simulator.instrument, quaternions, hwp=hwp)
        lbs.precompute_pointings(observation)
    with clock("sky scan"):
        maps = lbs.HealpixMap(
            values=sky_map, nside=settings.nside, coordinates=lbs.CoordinateSystem.Galactic
        )
        lbs.scan_map_in_observations(observation, maps=maps)
    with clock("dipole"):
        lbs.add_dipole_to_observations(observation, pos_and_vel=simulator.orbit)
    with clock("noise"):
        generators = [
            seeding.rng(settings.master_seed, "noise", simulator.channel.name, settings.seed, 0, n)
            for n in simulator.detector_names
        ]
        lbs.add_noise_to_observations(
            observation,
            "one_over_f",
            dets_random=generators,
            scale=settings.noise_scale,
            engine=NOISE_MODELS[simulator.noise_model],
            model=simulator.noise_model,
        )
    with clock("HWPSS"):
        add_2f(
            observation.tod,
            observation.hwp_angle,
            simulator.pol_angles_rad,
            np.full(simulator.n_detectors, settings.a2_k_cmb),
        )
    with clock("nonlinearity"):
        for index, g1 in enumerate(g1_per_k):
            apply_quadratic_nonlin_for_one_detector(
                observation.tod[index],
                nl_params=lbs.NonLinParams(
                    sampling_gaussian_loc=float(g1), sampling_gaussian_scale=0.0
                ),
                random=np.random.default_rng(0),
            )
    with clock("2f removal + notch"):
        angle = observation.hwp_angle
        pointing = SimpleNamespace(  # what the filter reads of a ChunkPointing
            hwp_angle_rad=angle,
            harmonic_templates=lambda harmonics, offset: harmonic_templates(
                angle, harmonics, offset
            ),
        )
        filtered = filter_tod(observation.tod, pointing, inner, simulator, settings)
    with clock("binning"):
        # the chunk without its margins: same quaternions, so the same pointings
        inner_observation, inner_hwp, _ = observation_and_hwp(first, n_samples)
        lbs.prepare_pointings(inner_observation, simulator.instrument, quaternions, inner_hwp)
        inner_observation.tod[:] = filtered
        result = lbs.make_binned_map(settings.nside, inner_observation)
    return result.binned_map


def run_naive(arguments, duration_s, cases, queue):
    simulator, settings, sky_map, draws = setup(arguments, duration_s)
    warm_simulator, warm_settings, *_ = setup(arguments, 600.0)
    naive_map(warm_simulator, warm_settings, sky_map, np.zeros(2), StageClock())
    clock = StageClock()
    started = time.perf_counter()
    maps = {sigma: naive_map(simulator, settings, sky_map, sigma * draws, clock) for sigma in cases}
    seconds = time.perf_counter() - started
    peak_mb = peak_rss_mb()
    queue.put((maps, seconds, dict(clock.seconds), peak_mb))


def run_workflow(arguments, duration_s, cases, queue):
    simulator, settings, sky_map, draws = setup(arguments, duration_s)
    warm_simulator, warm_settings, *_ = setup(arguments, 600.0)
    timed_accumulate(warm_simulator, warm_settings, sky_map, "linear")
    started = time.perf_counter()
    equations, _, clock = timed_accumulate(simulator, settings, sky_map, "linear")
    with clock("solve + sigma grid"):
        solved, _, good = solve_maps(equations, settings.max_condition_number)
        templates = split_solved_maps(solved, simulator.n_detectors, settings.a2_k_cmb)
        maps = {
            sigma: maps_for_sigma(solved[0], templates["templates"], draws, sigma)
            for sigma in cases
        }
    seconds = time.perf_counter() - started
    peak_mb = peak_rss_mb()
    queue.put(({**maps, "good": good}, seconds, dict(clock.seconds), peak_mb))


def in_subprocess(target, *args):
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=target, args=(*args, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def print_path(name, seconds, stages, peak_mb, samples):
    print(
        f"{name}: {seconds:7.1f} s, {samples / seconds:.3e} detector-samples/s, "
        f"{1e9 * seconds / samples:6.0f} ns per detector-sample, peak RSS {peak_mb:.0f} MB"
    )
    for stage, stage_s in stages.items():
        print(f"    {stage:22s} {stage_s:7.2f} s  {1e9 * stage_s / samples:6.0f} ns/sample")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--hours", type=float, default=24.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--sigmas", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2, 1e-1])
    parser.add_argument("--threads", type=int, default=1, help="FFT/pixelisation threads")
    parser.add_argument("--noise", choices=sorted(NOISE_MODELS), default="keshner")
    arguments = parser.parse_args()

    duration_s = arguments.hours * 3600.0
    cases = [0.0, *arguments.sigmas]
    naive, naive_s, naive_stages, naive_mb = in_subprocess(run_naive, arguments, duration_s, cases)
    workflow, workflow_s, workflow_stages, workflow_mb = in_subprocess(
        run_workflow, arguments, duration_s, cases
    )
    rate_hz = load_channel(arguments.channel).sampling_rate_hz
    samples = round(duration_s * rate_hz) * 2
    print(
        f"{arguments.channel}: {arguments.hours:g} h, {samples:.3e} detector-samples, "
        f"nside {arguments.nside}, noise {arguments.noise}, threads {arguments.threads}; "
        f"cases: nosys + sigma_g1 {arguments.sigmas}"
    )
    print_path(f"naive    ({len(cases)} simulations)", naive_s, naive_stages, naive_mb, samples)
    print_path("workflow (1 simulation) ", workflow_s, workflow_stages, workflow_mb, samples)
    tod_notch_binning = sum(
        seconds for stage, seconds in workflow_stages.items() if stage != "solve + sigma grid"
    )
    print(
        f"workflow TOD + notch + binning: {1e9 * tod_notch_binning / samples:.0f} ns per "
        "detector-sample (target <= 300)"
    )
    print(f"ratio naive / workflow = {naive_s / workflow_s:.1f} (target >= 10)")
    good = workflow["good"]
    for sigma in cases:
        seen = good & (naive[sigma][0] != -1.6375e30)
        difference = np.abs(naive[sigma][:, seen] - workflow[sigma][:, seen]).max()
        rms = np.sqrt(np.mean(workflow[sigma][:, seen] ** 2))
        print(
            f"  sigma_g1 = {sigma:7.1e}: max |naive - workflow| / rms = {difference / rms:.2e}"
            " (target < 1e-8)"
        )


if __name__ == "__main__":
    main()
