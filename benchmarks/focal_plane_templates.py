"""How the nonlinearity template of a channel averages down with its detector pairs.

One channel's seed-independent TOD (dipole + HWPSS, no foreground, no noise) through the
paper's filter (2f removal, notch, 60 s baselines) and the binned map-maker of all its N
pairs together (:func:`tod_maps.accumulate`), for several N chosen by
:func:`instrument.load_channel` (nested: each N holds the smaller ones). With T_k the
binned template of detector k at g1 = 1 1/K (``tod_maps.templates_from_terms``):

- random population (g1_k = sigma z_k, z_k independent N(0, 1)): the expected template
  power is sum_k C_ell(T_k), printed per multipole band;
- common population (g1_k = mu for every k): the power is C_ell(sum_k T_k).

Beside them, the variance a white noise would have in the same pixels, mean(1 / hits),
against N = 1: a template that averages down like the noise follows it, whatever the mask.

Both are pseudo-spectra of the observed pixels (BB, and the Q/U rms), printed beside the
N = 1 value; the cross-correlation coefficient of two detectors' templates,
C_ell(T_a, T_b) / sqrt(C_ell(T_a) C_ell(T_b)) at ell 2-40, is printed against their
focal-plane separation (the mechanism of what the common population keeps).

    python benchmarks/focal_plane_templates.py --channel M1-140 --days 1 --pairs 1 2 4 8
    python benchmarks/focal_plane_templates.py --positions field_of_view ...

With ``--separations-deg``, one pass instead: the first pair and, for each separation,
the two pairs nearest to it (layout of :mod:`focal_plane`), one of the first pair's
orientation field (``00A`` in ``001_002_030_00A_140_T``) and one of another, and the
correlation at ell 2-40 of every two detectors' templates against their separation.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import healpy as hp
import numpy as np
from common import A2_K_CMB, START_TDB, paper_settings

from hwp_tes_systematics.instrument.channels import load_channel, telescope_of
from hwp_tes_systematics.instrument.focal_plane import angular_separation_deg
from hwp_tes_systematics.io import reuse_freed_memory, use_threads
from hwp_tes_systematics.simulation.mapmaking import solve_maps
from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator
from hwp_tes_systematics.simulation.tod_maps import accumulate, split_solved_maps

FIELD_OF_VIEW_DEG = {"LFT": (9.0, 4.5), "MFT": (14.0, 14.0), "HFT": (14.0, 14.0)}  # config
BANDS = ((2, 11), (12, 40), (41, 100))


def orientation_of(detector: str) -> str:
    """The orientation field of a PTEP detector name (``001_002_030_00A_140_T``: ``00A``)."""
    return detector.split("_")[3]


def pairs_at_separations(name: str, separations_deg):
    """The channel (positions in the field of view) holding its first pair and, for each
    separation [deg], the pairs nearest to it from the first: one whose orientation field
    is the first pair's, one whose is another."""
    channel = load_channel(
        name, pairs="all", field_of_view_deg=FIELD_OF_VIEW_DEG[telescope_of(name)]
    )
    positions = channel.detector_positions
    separation = np.array(
        [angular_separation_deg(positions[0], positions[2 * i]) for i in range(channel.n_pairs)]
    )
    same = np.array(
        [
            orientation_of(channel.detectors[2 * i]) == orientation_of(channel.detectors[0])
            for i in range(channel.n_pairs)
        ]
    )
    chosen = [0]
    for target in separations_deg:
        for wanted in (True, False):
            excluded = np.isin(np.arange(channel.n_pairs), chosen) | (same != wanted)
            chosen.append(int(np.argmin(np.where(excluded, np.inf, np.abs(separation - target)))))
    detectors = [2 * i + k for i in chosen for k in (0, 1)]
    return dataclasses.replace(
        channel,
        detectors=tuple(channel.detectors[d] for d in detectors),
        detector_positions=tuple(positions[d] for d in detectors),
    )


def channel_templates(name, n_pairs, positions, days, nside, rate_hz, stride=1, channel=None):
    """(templates (n_det, 3, npix) [K_CMB at g1 = 1/K], good, hits, channel, seconds) of
    ``days`` of mission, one day in ``stride`` simulated (``channel``: these detectors
    instead of ``n_pairs`` chosen by :func:`load_channel`)."""
    fov = FIELD_OF_VIEW_DEG[telescope_of(name)] if positions == "field_of_view" else None
    if channel is None:
        channel = load_channel(name, pairs=n_pairs, field_of_view_deg=fov)
    plan = MissionPlan(START_TDB, days * 86400.0, 86400.0, rate_hz, stride)
    settings = paper_settings(plan, nside, A2_K_CMB, baseline_length_s=60.0, noise_scale=0.0)
    simulator = PairSimulator(channel, plan, nside, noise_model="keshner")
    started = time.perf_counter()
    sky_map = np.zeros((3, hp.nside2npix(nside)))
    equations = accumulate(simulator, settings, sky_map)
    maps, _, good = solve_maps(equations, settings.max_condition_number)
    solved = split_solved_maps(maps, simulator.n_detectors, A2_K_CMB)
    return solved["templates"], good, equations.hits, channel, time.perf_counter() - started


def pseudo_bb(maps_iqu: np.ndarray, good: np.ndarray, lmax: int, other=None) -> np.ndarray:
    """BB pseudo-spectrum (cross with ``other`` if given) of the observed pixels."""

    def masked(m):
        return np.where(good, m, 0.0)

    first = masked(maps_iqu)
    second = first if other is None else masked(other)
    return hp.anafast(first, second, lmax=lmax, iter=0)[2]


def band_means(cl: np.ndarray) -> list[float]:
    return [float(cl[lo : hi + 1].mean()) for lo, hi in BANDS]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--channel", default="M1-140")
    parser.add_argument("--days", type=float, default=1.0)
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--rate-hz", type=float, default=19.0)
    parser.add_argument("--stride", type=int, default=1, help="simulate one day in this many")
    parser.add_argument("--pairs", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument(
        "--positions", choices=("boresight", "field_of_view"), default="field_of_view"
    )
    parser.add_argument(
        "--separations-deg",
        type=float,
        nargs="+",
        help="one pass of the first pair and the pairs nearest these separations from it",
    )
    args = parser.parse_args(argv)
    use_threads(1)
    reuse_freed_memory()  # as the fixed_pass job: the chunks' arrays without page faults
    lmax = 2 * args.nside
    print(
        f"{args.channel}, {args.days:g} days (one in {args.stride}) at {args.rate_hz:g} Hz, "
        f"nside {args.nside}, "
        f"positions {args.positions}; BB pseudo-spectra [K^2 at g1 = 1/K] in ell bands {BANDS}"
    )
    if args.separations_deg:
        channel = pairs_at_separations(args.channel, args.separations_deg)
        templates, good, _, channel, seconds = channel_templates(
            args.channel,
            None,
            "field_of_view",
            args.days,
            args.nside,
            args.rate_hz,
            args.stride,
            channel,
        )
        print(f"{channel.n_pairs} pairs in one pass ({seconds:.0f} s), observed {good.mean():.1%}")
        print_correlations(templates, good, channel)
        return
    runs = {}
    for n_pairs in sorted(args.pairs):
        runs[n_pairs] = channel_templates(
            args.channel, n_pairs, args.positions, args.days, args.nside, args.rate_hz, args.stride
        )
    # one mask for every N: the pixels all of them observe (a pair's sky grows with N),
    # then those of them the first pair observes at least as often as its median pixel
    # (a pixel at the edge of one pair's sky has few hits and a large template, which
    # another pair's hits dilute: coverage, not averaging)
    observed = np.logical_and.reduce([run[1] for run in runs.values()])
    first_hits = runs[min(runs)][2]
    well_observed = observed & (first_hits >= np.median(first_hits[observed]))
    for label, good in (("observed by every N", observed), ("well observed", well_observed)):
        print(f"pixels {label}: {good.mean():.1%} of the sky")
        reference = None
        for n_pairs, (templates, seen, hits, channel, seconds) in runs.items():
            common = templates.sum(axis=0)
            per_detector = [pseudo_bb(t, good, lmax) for t in templates]
            random_cl = np.sum(per_detector, axis=0)
            common_cl = pseudo_bb(common, good, lmax)
            qu_random = np.sqrt(np.sum([np.mean(t[1:, good] ** 2) for t in templates]))
            qu_common = np.sqrt(np.mean(common[1:, good] ** 2))
            white = float(np.mean(1.0 / hits[good]))  # a white noise's map variance, per hit
            row = band_means(random_cl) + band_means(common_cl) + [qu_random, qu_common, white]
            reference = reference or row
            ratios = np.array(row) / np.array(reference)
            print(
                f"  N = {n_pairs:3d} pairs ({seconds:.0f} s, observed {seen.mean():.1%}): "
                f"random BB {' '.join(f'{v:.3g}' for v in row[:3])} "
                f"(x{' '.join(f'{r:.3f}' for r in ratios[:3])}); "
                f"common BB {' '.join(f'{v:.3g}' for v in row[3:6])} "
                f"(x{' '.join(f'{r:.3f}' for r in ratios[3:6])}); "
                f"Q/U rms random {row[6]:.3g} (x{ratios[6]:.3f}) common {row[7]:.3g} "
                f"(x{ratios[7]:.3f}); white-noise variance mean(1/hits) x{ratios[8]:.3f}"
            )
    if channel.detector_positions is not None:
        print_correlations(templates, good, channel)


def print_correlations(templates, good, channel) -> None:
    """The correlation C(T_a, T_b) / sqrt(C(T_a) C(T_b)) summed over ell 2-40 of every two
    detectors' templates, with their focal-plane separation, nearest first."""
    autos = [pseudo_bb(t, good, 40)[2:].sum() for t in templates]
    rows = []
    for a in range(len(templates)):
        for b in range(a + 1, len(templates)):
            cross = pseudo_bb(templates[a], good, 40, templates[b])[2:].sum()
            separation = angular_separation_deg(
                channel.detector_positions[a], channel.detector_positions[b]
            )
            rows.append((separation, cross / np.sqrt(autos[a] * autos[b]), a, b))
    print("template correlation at ell 2-40 against the separation of two detectors:")
    for separation, coefficient, a, b in sorted(rows):
        first, second = channel.detectors[a], channel.detectors[b]
        kind = "same" if orientation_of(first) == orientation_of(second) else "other"
        print(
            f"  {first} x {second}: separation {separation:5.1f} deg, orientation {kind:5s}, "
            f"correlation {coefficient:+.3f}"
        )


if __name__ == "__main__":
    main()
