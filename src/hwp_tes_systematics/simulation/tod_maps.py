"""TOD -> HWP-harmonic removal -> 4f notch -> baselines -> binned normal equations, for one
detector pair, linear in g1.

The nonlinear TOD of detector k is d_k + g1_k d_k^2. The HWP-harmonic removal, notch
filter, baseline removal F and binning M are linear, so the map for any draw of g1 is

    m(g1) = M F d + sum_k g1_k M F (d_k^2) = m_nosys + sum_k g1_k T_k.

Writing d_k = s_k + A_2 h_k (s: sky + dipole + noise, h = cos 2(chi - theta_k) the unit
HWPSS), d_k^2 = s_k^2 + 2 A_2 s_k h_k + A_2^2 h_k^2, so the template is the sum of three
binned terms, T_k = T_ss + 2 A_2 T_sh + A_2^2 T_hh, all three kept: the template for
any other HWPSS amplitude follows without a new simulation. The mission is processed
chunk by chunk (normal equations accumulated), so memory does not grow with its
duration. Used by the pair_maps and notch_effect stages, the benchmarks and the tests.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass

import healpy as hp
import numpy as np
import psutil
from tqdm import tqdm

from ..config import simulated_rate_hz
from ..timing import StageClock
from .baselines import remove_baselines
from .chunk_binning import (
    ExtraBinning,
    bin_chunk,
    bin_extra_binnings,
    bin_streams,
    demodulated_streams,
    share_binned_matrices,
)
from .demodulation import DemodulatedEquations
from .mapmaking import NormalEquations, PixelMoments
from .notch import chunk_span
from .tod import MissionPlan, PairSimulator
from .tod_filter import baseline_samples_of, filter_offsets

log = logging.getLogger(__name__)

# From this resolution up the accumulations use NESTED pixels (measured, one M1-140 pair-day:
# at nside 512 binning 97 -> 63 ns and moments 63 -> 45 ns per sample for ~33 ns of
# NESTED pixel computation; at nside 64, where the maps fit the caches, a net loss of ~5 %)
NESTED_FROM_NSIDE = 256
# the terms of d^2 = s^2 + 2 A_2 s h + A_2^2 h^2 binned separately (see the module docstring)
TEMPLATE_TERMS = ("s*s", "s*h", "h*h")
# the calibration TODs (a reference map, noise realizations) are filtered in single
# precision: they measure ratios of spectra, which a relative rounding of ~1e-7 cannot
# move, and their FFTs take half the time (measured: 31 against 66 ns per row-sample)
CALIBRATION_DTYPE = np.float32
# memory a pass holds per detector and sample of a chunk (margins included) [bytes], and
# beside the chunks: measured on M1-140 fixed passes of one 19 Hz day at nside 64 with 2
# reference noise realizations, 1.42 / 2.40 / 4.30 GB peak for 1 / 2 / 4 pairs
# (docs/physics/focal_plane.md), with a margin
CHUNK_BYTES_PER_DETECTOR_SAMPLE = 320
PASS_BASE_BYTES = 0.6e9


@dataclass
class PairMapSettings:
    """Everything one (channel, seed) job needs besides the sky."""

    master_seed: int
    seed: int
    nside: int
    plan: MissionPlan
    a2_k_cmb: float
    notch_width_divisor: float | None  # None: no notch
    notch_margin_s: float
    max_condition_number: float
    removed_hwp_harmonics: tuple[int, ...] = (2,)
    noise_scale: float = 1.0
    baseline_length_s: float | None = None
    threads: int = 1

    @classmethod
    def from_config(
        cls, config: dict, channel, seed: int, a2_k_cmb: float, threads: int = 1, **changes
    ):
        """The settings of a (channel, seed) job of ``config``; ``changes`` replace fields
        (a benchmark's own plan, nside or noise scale)."""
        simulation = config["simulation"]
        settings = cls(
            master_seed=config["master_seed"],
            seed=seed,
            nside=config["maps"]["nside"],
            plan=MissionPlan(
                start_time_tdb=simulation["mission_start_tdb"],
                duration_s=simulation["duration_days"] * 86400.0,
                chunk_duration_s=simulation["chunk_duration_s"],
                sampling_rate_hz=simulated_rate_hz(config, channel),
                chunk_stride=simulation["chunk_stride"],
            ),
            a2_k_cmb=a2_k_cmb,
            notch_width_divisor=config["notch"]["width_divisor"],
            notch_margin_s=config["notch"]["margin_s"],
            max_condition_number=config["maps"]["max_condition_number"],
            removed_hwp_harmonics=tuple(config["maps"]["removed_hwp_harmonics"]),
            noise_scale=simulation["noise_scale"],
            baseline_length_s=config["maps"]["baseline_length_s"],
            threads=threads,
        )
        return dataclasses.replace(settings, **changes)


@dataclass
class Calibration:
    """TODs that measure what the filter does (the map-domain fixed pass), binned into their
    own normal equations on every ``every_chunks``-th chunk only (chunk index divisible by
    it): each map of ``references_iqu_k`` scanned alone, then ``noise_realizations``
    realizations of the detector noise n (scale 1; streams ``noise_seed``,
    ``noise_seed`` - 1, ...) and, with ``hwpss_noise``, each one's product h n with the
    unit HWPSS (the noise of the template's s h term): realization by realization n, h n
    after the filter, then the same before it. The filter's transfer and noise shaping
    are ratios of binned maps; the noise's is an expectation, which one realization
    measures poorly at low ell (the notch removes particular TOD modes: two realizations
    differ by 30 % to 3x at ell 2-11), hence several. With ``template_references`` the
    references' parts of the template follow them, as a map-maker other than the binned
    one sees them (:func:`fixed_maps.fixed_passes` with demodulated variants): each
    reference times the unit HWPSS, h x (the seed's CMB in the s h term), then each times
    twice the pass's own noiseless signal, 2 s_f x (the seed's CMB in the s^2 term); and
    ``static_sky`` bins s_f unfiltered (the map 2 s_f x is predicted from)."""

    nside: int
    references_iqu_k: tuple
    noise_seed: int
    every_chunks: int = 1
    hwpss_noise: bool = False
    noise_realizations: int = 1
    template_references: bool = False

    def __post_init__(self):
        if self.every_chunks < 1:
            raise ValueError(f"calibration every_chunks = {self.every_chunks}: expected >= 1")
        if self.noise_realizations < 1:
            raise ValueError(
                f"calibration noise_realizations = {self.noise_realizations}: expected >= 1"
            )
        self.equations = NormalEquations(self.nside, self.n_reference_tods + 2 * self.n_noise_tods)
        self.static_sky = NormalEquations(self.nside, 1) if self.template_references else None

    @property
    def n_reference_tods(self) -> int:
        """The reference TODs: each reference scanned alone, then (``template_references``)
        each times the unit HWPSS h, then each times 2 s_f."""
        return len(self.references_iqu_k) * (3 if self.template_references else 1)

    @property
    def kinds(self) -> int:
        """Noise TODs per realization: n, and h n with ``hwpss_noise``."""
        return 2 if self.hwpss_noise else 1

    @property
    def n_noise_tods(self) -> int:
        """The noise TODs binned filtered and unfiltered (each): kinds x realizations."""
        return self.kinds * self.noise_realizations

    def includes(self, chunk: int) -> bool:
        return chunk % self.every_chunks == 0


def calibration_stack(
    calibration, simulator, settings, pointing, chunk, hwpss, signal, inner, clock
):
    """(the chunk's calibration TODs before the filter, (rows, n_det, n) in
    CALIBRATION_DTYPE: each reference map scanned alone, with
    ``calibration.template_references`` then each times h and each times 2 ``signal``
    (the pass's s_f), then per realization n and, with ``calibration.hwpss_noise``, h n;
    a copy of the noise TODs' ``inner`` samples, to be binned unfiltered: the stack is
    filtered in place)."""
    n_references = calibration.n_reference_tods
    stack = np.empty(
        (n_references + calibration.n_noise_tods, *hwpss.shape), dtype=CALIBRATION_DTYPE
    )
    with clock("reference scans"):
        scanned = len(calibration.references_iqu_k)
        for row, reference_iqu_k in enumerate(calibration.references_iqu_k):
            stack[row] = simulator.scan_sky(pointing, reference_iqu_k)
            if calibration.template_references:  # the reference's parts of the template
                np.multiply(stack[row], hwpss, out=stack[scanned + row])  # of s h
                np.multiply(stack[row], 2.0 * signal, out=stack[2 * scanned + row])  # of s^2
    with clock("noise"):
        for realization in range(calibration.noise_realizations):
            row = n_references + realization * calibration.kinds
            stack[row] = simulator.noise(
                pointing, settings.master_seed, calibration.noise_seed - realization, chunk
            )
            if calibration.hwpss_noise:  # the noise of the s h term
                np.multiply(stack[row], hwpss, out=stack[row + 1])
    return stack, stack[n_references:, :, inner].copy()


def chunk_tods(
    simulator: PairSimulator,
    settings: PairMapSettings,
    sky_iqu_k: np.ndarray,
    clock: StageClock | None = None,
) -> Iterator[tuple[object, slice, np.ndarray]]:
    """Yield (chunk index, pointing, inner slice, s, h) chunk by chunk, with margins:
    s = sky + dipole + noise [K_CMB] and h = cos 2(chi - theta_k) the unit HWPSS, so that
    the total TOD is d = s + A_2 h."""
    clock = clock or StageClock()
    chunks = settings.plan.chunks()
    for chunk, first, n_samples in tqdm(
        chunks, desc=simulator.channel.name, mininterval=10, disable=len(chunks) < 2
    ):
        start, n_simulated, inner = chunk_span(
            first, n_samples, settings.plan.sampling_rate_hz, settings.notch_margin_s
        )
        with clock("pointing"):
            pointing = simulator.pointing(start, n_simulated)
        with clock("sky scan"):
            tod = simulator.scan_sky(pointing, sky_iqu_k)
        with clock("dipole"):
            tod += simulator.dipole(pointing)
        if settings.noise_scale != 0.0:  # 0: noiseless (the map-domain fixed pass)
            with clock("noise"):
                tod += simulator.noise(
                    pointing, settings.master_seed, settings.seed, chunk, settings.noise_scale
                )
        with clock("HWPSS"):
            unit_hwpss = simulator.hwpss(pointing, 1.0)
        yield chunk, pointing, inner, tod, unit_hwpss


def detector_weights(simulator: PairSimulator) -> np.ndarray:
    """w_k = 1 / sigma_k^2 with sigma_k = NET_k sqrt(f_s) [K^-2] (as litebird_sim's binner)."""
    sigma_k = np.array([d.net_ukrts for d in simulator.detectors]) * 1e-6
    return 1.0 / (sigma_k**2 * simulator.plan.sampling_rate_hz)


def accumulate(
    simulator,
    settings,
    sky_iqu_k,
    g1_per_k=None,
    on_chunk=None,
    references_iqu_k=(),
    clock: StageClock | None = None,
    template_terms: bool = True,
    moments: PixelMoments | None = None,
    calibration: Calibration | None = None,
    demodulated: DemodulatedEquations | None = None,
    extra_binnings: tuple[ExtraBinning, ...] = (),
) -> NormalEquations:
    """Normal equations of the filtered TOD (F = notch after HWP-harmonic removal).

    g1_per_k None: the linear decomposition, TODs [F d, then for each of the terms s^2,
    s h, h^2 of d^2 (see the module docstring) one TOD per detector]; otherwise the
    direct nonlinear simulation, one TOD F (d + g1 d^2).
    Each map in ``references_iqu_k`` adds the TOD F(scan of that map) at the end: a
    sky component alone (input CMB, foregrounds) through the same pointing, filter and
    binning, the references of the component-separation residuals.
    ``on_chunk(samples_done, rss_mb)`` is called after each chunk (benchmarks);
    ``clock`` collects the wall-clock time per stage (logged at the end).
    ``template_terms`` False skips the three terms (a channel without systematics);
    ``moments``, if given, accumulates the per-detector moments of the HWPSS
    (:class:`mapmaking.PixelMoments`) from the same pointing;
    ``calibration``, if given, receives its TODs (:class:`Calibration`) on its chunks.
    ``demodulated``, if given, also receives every filtered TOD through HWP demodulation
    and a low-pass (:mod:`demodulation`; baselines, if any, removed from its intensity
    stream only: the low-pass already removes offsets from Q and U): the same TODs, with
    another map-maker.
    ``extra_binnings``: further map-makers (:class:`ExtraBinning`) binned from the same
    TODs, at other resolutions and baseline lengths; their equations are created here.
    """
    clock = clock or StageClock()
    check_chunk_memory(simulator, settings)
    _check_map_makers(settings, calibration, demodulated, extra_binnings)
    n_det = simulator.n_detectors
    linear = g1_per_k is None
    n_terms = len(TEMPLATE_TERMS) if linear and template_terms else 0
    n_binned = 1 + n_terms + len(references_iqu_k)  # rows of the stack binned in ``equations``
    equations = NormalEquations(settings.nside, 1 + n_terms * n_det + len(references_iqu_k))
    binned_of = _create_extra_equations(equations, settings.nside, calibration, extra_binnings)
    nested = settings.nside >= NESTED_FROM_NSIDE
    primary_offset = settings.baseline_length_s is not None
    offsets = {primary_offset} | {e.baseline_length_s is not None for e in extra_binnings}
    weights = detector_weights(simulator)
    # a term's TOD is binned once per detector, with that detector's samples only
    owners = [None] + [k for _ in range(n_terms) for k in range(n_det)]
    binned = (_rows_of(n_terms, n_det, equations.n_tods), owners + [None] * len(references_iqu_k))
    peak_rss_mb = 0.0
    unfiltered_noise = None  # the calibration noise TODs before the filter, on its chunks
    for chunk, pointing, inner, signal, hwpss in chunk_tods(simulator, settings, sky_iqu_k, clock):
        calibrating = calibration is not None and calibration.includes(chunk)
        with clock("pixels"):
            pixels_of = _chunk_pixels(simulator, settings.nside, extra_binnings, pointing, inner)
        moment_targets = [(moments, settings.nside)]
        moment_targets += [(extra.moments, extra.nside) for extra in extra_binnings]
        _add_moments(moment_targets, pixels_of, pointing, inner, weights, simulator, hwpss, clock)
        # all TODs of the chunk in one array, for one batched 2f removal + notch
        with clock("nonlinearity terms"):
            unfiltered = np.empty((n_binned, *signal.shape))
            _fill_signal_terms(unfiltered, signal, hwpss, settings.a2_k_cmb, n_terms, g1_per_k)
        with clock("reference scans"):
            for index, reference_iqu_k in enumerate(references_iqu_k, start=1 + n_terms):
                simulator.scan_sky(pointing, reference_iqu_k, out=unfiltered[index])
        if calibrating:
            calibration_tods, unfiltered_noise = calibration_stack(
                calibration, simulator, settings, pointing, chunk, hwpss, signal, inner, clock
            )
            if calibration.static_sky is not None:  # s_f as it is, binned
                with clock("binning"):
                    calibration.static_sky.add(
                        pixels_of[settings.nside],
                        pointing.cos_2alpha[:, inner],
                        pointing.sin_2alpha[:, inner],
                        weights,
                        simulator.pol_efficiency,
                        [signal[:, inner]],
                    )
        del hwpss, signal
        with clock("2f removal + notch"):
            notched_of = filter_offsets(unfiltered, offsets, pointing, simulator, settings)
            notched = notched_of[primary_offset]
            del unfiltered
            calibration_of = dict.fromkeys(offsets)
            if calibrating:
                calibration_of = filter_offsets(
                    calibration_tods, offsets, pointing, simulator, settings
                )
                del calibration_tods
        rates = (settings.plan.sampling_rate_hz, simulator.channel.hwp_frequency_hz)
        detector = (weights, simulator.pol_efficiency)
        if demodulated is not None:
            bin_streams(
                demodulated,
                demodulated_streams(notched, pointing, inner, rates, settings.threads, clock),
                binned,
                pointing.pixels[:, inner],
                pointing,
                inner,
                detector,
                baseline_samples_of(settings),
                clock,
            )
        angles = (pointing.cos_2alpha[:, inner], pointing.sin_2alpha[:, inner], *detector)
        bin_extra_binnings(
            extra_binnings,
            (calibrating, pixels_of, angles, binned, unfiltered_noise),
            (notched_of, calibration_of),
            (pointing, inner, rates, settings.threads, clock),
        )
        samples = baseline_samples_of(settings)
        filtered = remove_baselines(notched[..., inner], samples)
        calibration_filtered = None
        if calibrating:
            calibration_filtered = remove_baselines(
                calibration_of[primary_offset][..., inner], samples
            )
        del notched, notched_of, calibration_of
        with clock("binning"):
            bin_chunk(
                equations,
                calibration.equations if calibrating else None,
                pixels_of[settings.nside],
                angles,
                binned,
                filtered,
                calibration_filtered,
                unfiltered_noise,
            )
        del filtered, calibration_filtered
        unfiltered_noise = None
        rss_mb = psutil.Process().memory_info().rss / 2**20
        peak_rss_mb = max(peak_rss_mb, rss_mb)
        if on_chunk is not None:
            on_chunk(inner.stop - inner.start, rss_mb)
    if nested:
        _nest_to_ring(equations, moments, calibration, extra_binnings)
    share_binned_matrices(extra_binnings, binned_of, calibration)
    log.info(
        "%s seed %d: peak RSS during chunks %.0f MB; time per stage: %s",
        simulator.channel.name,
        settings.seed,
        peak_rss_mb,
        clock.summary(settings.plan.simulated_samples * n_det),
    )
    return equations


def _check_map_makers(settings, calibration, demodulated, extra_binnings) -> None:
    """The map-maker combinations :func:`accumulate` cannot make, as clear errors."""
    if demodulated is not None and calibration is not None:
        raise ValueError("accumulate: demodulated maps of calibration TODs are not supported")
    if demodulated is not None and extra_binnings:
        raise ValueError("accumulate: demodulated maps with extra binnings are not supported")
    if any(e.demodulated for e in extra_binnings) and settings.notch_width_divisor is None:
        raise ValueError("accumulate: a demodulated extra binning needs the notch's margins")
    if calibration is not None and calibration.template_references and settings.noise_scale:
        raise ValueError(
            "accumulate: the calibration's template references take the TOD as s_f, "
            f"which needs a noiseless pass (noise_scale = {settings.noise_scale})"
        )


def _create_extra_equations(equations, nside: int, calibration, extra_binnings) -> dict:
    """Create the extra binnings' equations; returns {nside: (binned equations, binned
    calibration equations)} of the binned map-makers. The binned ones come first: a
    demodulated one takes M and the unfiltered noise from the binned one of its
    resolution (the same samples), or bins its own."""
    binned_of = {nside: (equations, calibration.equations if calibration else None)}
    for extra in (e for e in extra_binnings if not e.demodulated):
        extra.equations = NormalEquations(extra.nside, equations.n_tods)
        if calibration is not None:
            extra.calibration_equations = NormalEquations(extra.nside, calibration.equations.n_tods)
        binned_of.setdefault(extra.nside, (extra.equations, extra.calibration_equations))
    for extra in (e for e in extra_binnings if e.demodulated):
        extra.equations = DemodulatedEquations(extra.nside, equations.n_tods)
        if calibration is not None:
            n_filtered = calibration.equations.n_tods - calibration.n_noise_tods
            extra.calibration_equations = DemodulatedEquations(extra.nside, n_filtered)
        if extra.nside not in binned_of:
            extra.matrix_equations = NormalEquations(extra.nside, 0)
            if calibration is not None:
                extra.white_equations = NormalEquations(extra.nside, calibration.n_noise_tods)
    return binned_of


def _chunk_pixels(simulator, nside: int, extra_binnings, pointing, inner) -> dict:
    """{nside: (n_det, n_inner) pixels} of the chunk's inner samples for every map-maker.
    At high resolution NESTED pixels (neighbours on the sky are neighbours in memory:
    fewer cache misses), those of a coarser resolution by a shift, converted to RING at
    the end (:func:`_nest_to_ring`)."""
    if nside >= NESTED_FROM_NSIDE:
        nest = simulator.pixels_at(pointing, nside, inner, nest=True)
        pixels_of = {nside: nest}
        for extra in extra_binnings:
            shift = 2 * ((nside // extra.nside).bit_length() - 1)
            pixels_of.setdefault(extra.nside, nest >> shift)
        return pixels_of
    pixels_of = {nside: pointing.pixels[:, inner]}
    for extra in extra_binnings:
        if extra.nside not in pixels_of:
            pixels_of[extra.nside] = simulator.pixels_at(pointing, extra.nside, inner)
    return pixels_of


def _add_moments(targets, pixels_of, pointing, inner, weights, simulator, hwpss, clock) -> None:
    """Add the chunk's HWPSS moments to each distinct :class:`mapmaking.PixelMoments` of
    ``targets`` [(moments or None, nside)] (a resolution's moments are added once)."""
    added = set()
    for target, nside in targets:
        if target is None or id(target) in added:
            continue
        added.add(id(target))
        with clock("HWPSS moments"):
            target.add(
                pixels_of[nside],
                pointing.cos_2alpha[:, inner],
                pointing.sin_2alpha[:, inner],
                weights,
                simulator.pol_efficiency,
                hwpss[:, inner],
            )


def _fill_signal_terms(unfiltered, signal, hwpss, a2_k_cmb: float, n_terms: int, g1_per_k):
    """Rows 0..n_terms of the chunk's stack, in place: d = s + A_2 h, then the terms s^2,
    s h, h^2 of d^2 (``n_terms`` 3), or, with ``g1_per_k``, d + g1 d^2 alone."""
    tod = unfiltered[0]
    np.multiply(hwpss, a2_k_cmb, out=tod)
    tod += signal
    if n_terms:
        np.square(signal, out=unfiltered[1])
        np.multiply(signal, hwpss, out=unfiltered[2])
        np.square(hwpss, out=unfiltered[3])
    elif g1_per_k is not None:
        tod += np.asarray(g1_per_k)[:, None] * tod**2


def chunk_memory_bytes(n_detectors: int, settings) -> float:
    """Peak memory of a pass whose chunks hold ``n_detectors`` detectors [bytes]:
    PASS_BASE_BYTES + CHUNK_BYTES_PER_DETECTOR_SAMPLE x detectors x samples of a chunk
    with its margins (measured, see the constants)."""
    plan = settings.plan
    margins_s = 2 * (settings.notch_margin_s or 0.0)
    samples = plan.samples_per_chunk + round(margins_s * plan.sampling_rate_hz)
    return PASS_BASE_BYTES + CHUNK_BYTES_PER_DETECTOR_SAMPLE * n_detectors * samples


def check_chunk_memory(simulator, settings) -> None:
    """A clear MemoryError before the first chunk when the chunks of all the channel's
    detectors would not fit the memory available now (:func:`chunk_memory_bytes`)."""
    needed = chunk_memory_bytes(simulator.n_detectors, settings)
    available = psutil.virtual_memory().available
    if needed > available:
        raise MemoryError(
            f"{simulator.channel.name}: {simulator.n_detectors} detectors "
            f"(instrument.pairs_per_channel) in chunks of {settings.plan.chunk_duration_s:g} s "
            f"(simulation.chunk_duration_s) at {settings.plan.sampling_rate_hz:g} Hz need about "
            f"{needed / 1e9:.1f} GB, {available / 1e9:.1f} GB are available: use fewer pairs "
            "or shorter chunks"
        )


def _nest_to_ring(equations, moments, calibration, extra_binnings) -> None:
    """Reorder every accumulation of :func:`accumulate` from NESTED to RING pixels (each
    pixel's numbers unchanged: the same additions in the same order)."""
    targets = [equations, moments]
    if calibration is not None:
        targets += [calibration.equations, calibration.static_sky]
    for extra in extra_binnings:
        targets += [extra.equations, extra.moments, extra.calibration_equations]
        targets += [extra.white_equations, extra.matrix_equations]
    done = set()
    for target in targets:
        if target is None or id(target) in done:
            continue
        done.add(id(target))
        target.reorder(hp.ring2nest(target.nside, np.arange(target.npix)))


def _rows_of(n_terms: int, n_det: int, n_tods: int) -> list[int]:
    """Row of the filtered stack that each binned TOD comes from (a term's row is binned
    once per detector)."""
    rows = [0]
    for term in range(1, 1 + n_terms):
        rows += [term] * n_det
    return rows + list(range(1 + n_terms, 1 + n_terms + n_tods - len(rows)))


def term_weights(a2_k_cmb: float) -> tuple[float, float, float]:
    """The weights of the TEMPLATE_TERMS in T_k = T_ss + 2 A_2 T_sh + A_2^2 T_hh: (1, 2 A_2,
    A_2^2); A_2 [K_CMB]."""
    return 1.0, 2.0 * a2_k_cmb, a2_k_cmb**2


def templates_from_terms(terms: np.ndarray, a2_k_cmb: float) -> np.ndarray:
    """T_k = T_ss + 2 A_2 T_sh + A_2^2 T_hh [K_CMB^2], (n_det, 3, npix) from the terms
    (3, n_det, 3, npix) in TEMPLATE_TERMS order (:func:`term_weights`); A_2 [K_CMB]."""
    _, sh_weight, hh_weight = term_weights(a2_k_cmb)
    return terms[0] + sh_weight * terms[1] + hh_weight * terms[2]


def split_solved_maps(
    maps: np.ndarray, n_det: int, a2_k_cmb: float, template_terms: bool = True
) -> dict[str, np.ndarray]:
    """The solved maps of a linear accumulation by name: nosys (3, npix); template_terms
    (3, n_det, 3, npix) (zeros if the accumulation had none, ``template_terms`` False);
    templates (n_det, 3, npix) at A_2 = ``a2_k_cmb``; references (n_refs, 3, npix), in
    the order given to :func:`accumulate`."""
    n_terms = len(TEMPLATE_TERMS)
    n_binned = n_terms * n_det if template_terms else 0
    if template_terms:
        terms = maps[1 : 1 + n_binned].reshape(n_terms, n_det, *maps.shape[1:])
    else:
        terms = np.zeros((n_terms, n_det, *maps.shape[1:]))
    seen = maps[0] != hp.UNSEEN
    templates = np.where(seen, templates_from_terms(terms, a2_k_cmb), hp.UNSEEN)
    return {
        "nosys": maps[0],
        "template_terms": terms,
        "templates": templates,
        "references": maps[1 + n_binned :],
    }
