"""Realizations in the map domain: one seed-independent TOD pass per channel, then each
seed as map products (the fast path to one year; the full-TOD path stays the reference).

Of the TOD d = s + A_2 h, s = fg + dipole + CMB_seed + n_seed, only the CMB draw and the
noise depend on the seed. Writing s = s_f + x (s_f = fg + dipole, x = CMB_seed + n_seed),
the fixed pass simulates once, without CMB or noise, through the same HWP-harmonic
removal, notch, baselines and binning as the full path (:func:`tod_maps.accumulate`):

* m_f = bin F(s_f + A_2 h), the foreground reference bin F(fg), the template terms of s_f
  (s_f^2, s_f h, h^2 per detector);
* the HWPSS moments per detector k and pixel p (:class:`mapmaking.PixelMoments`):
  M_k = sum w a^T a, H_k = sum w h a^T a, Q_k = sum w h^2 a^T a (M = sum_k M_k);
* the filter's action on a reference CMB realization, T_ell = C_ell(bin F CMB, CMB) /
  C_ell(CMB) (TT, EE, BB), and on ``simulation.noise_reference_realizations`` reference
  noise realizations, the shaping S_ell (~ sqrt(sum C_ell(bin F n) / sum C_ell(bin n)),
  calibrated so that shaping bin n gives the pseudo-spectrum of bin F n on the observed
  pixels), and the shaping S^h_ell of the same noise times the unit HWPSS, h n (the s h
  term's noise: the filter does not act on h n as on n), each an expectation that one
  realization measures poorly at low ell (docs/physics/map_domain.md: with one
  realization and S_ell for both, H3-402's one-month seed part came out 17 % high, with
  four and S^h 10 %); all from every
  ``simulation.calibration_every_chunks``-th chunk (1 by default: a subset of the days
  biases the low-ell shaping, benchmarks/calibration_stride_validation.py).

Each seed then costs map operations only:

    nosys            = m_f + T CMB_seed + S M^-1 sum_k b_k
    s h term of k    = (s_f h term of k) + T^h M^-1 H_k CMB_seed + S^h M^-1 c_k
    cmb_reference    = T CMB_seed

and, for a demodulated map-maker only, the s^2 term of k gets the seed's 2 s_f CMB_seed
as detector k's share of S^s P(s_f, CMB_seed) (:func:`static_sky_product`,
:func:`demodulated_shares`; S^s, a shaping as S, measured in the pass: a transfer T^s
of cross spectra gave 48-76 % of the full path's B power at 30 days, as the filter's
E-to-B mixing is no transfer; benchmarks/s2_seed_part_validation.py),

with (b_k, c_k) ~ N(0, noise_scale^2 [[M_k, H_k], [H_k, Q_k]]) the binned white noise and
binned h n of detector k, drawn jointly per pixel (exact for white noise: b_k = sum w a^T n,
c_k = sum w a^T h n, var(n) = 1 / w), T^h = 1 for the binned map-maker (the filter's
action on h CMB is left out, below) and, for HWP demodulation (``demodulated_variants``
of :func:`fixed_passes`), measured in the pass: the demodulated h x reference CMB against
M^-1 sum_k H_k of it, ~0 on a band-limited sky (h CMB sits at 2 f_HWP, which
demodulation moves to 2 and 6 f_HWP and its low-pass removes; a nearest-pixel scan's
steps put sky power there: ``simulation.sky_scanning``), and T, S, T^h applied to the
T, E, B a_lm up to
``simulation.filter_lmax`` (the map's whole band by default; the analysis reads nothing
above component_separation lmax, so at nside 512 stopping there saves most transforms).
What the seeds of a channel share (noise factors, M^-1, H_k) is computed once
(:class:`SeedOperators`). The binning
reads a TOD at 0 and 4 f_HWP, where the notch removes the noise's (and h n's) sky-scale
part: without S the map-domain noise is too high (by 2x in variance at 1 day, nside 32).
As the residual subtracts cmb_reference, the CMB cancels there exactly and enters only
through the HILC weights, as in the full path.

Approximated, and measured against the full path (tests/test_map_domain.py,
benchmarks/map_domain_validation.py): the filter as multipole functions (an
along-scan filter; good on a large observed sky, poor on a few hours' stripe); white
noise (the 1/f part is left out: it reaches I, not Q/U, with a HWP); the filter's
action on h CMB (7-13 % of that part); for the binned map-maker, the seed part of the
s^2 term, 2 s_f x + x^2 (2 % of the s h part: s_f is the dipole and foregrounds, mK,
against A_2 = 0.16-3.8 K; demodulation removes the s h part's sky and keeps it).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import h5py
import healpy as hp
import numpy as np

from .. import config as cfg
from .. import seeding
from ..io import atomic_path
from ..sky import cmb as sky_cmb
from ..sky import harmonics
from ..sky.harmonics import BandLimitedSky
from .mapmaking import MATRIX_ENTRIES, PixelMoments, solve_maps, symmetric_matrices
from .tod_maps import (
    TEMPLATE_TERMS,
    Calibration,
    ExtraBinning,
    accumulate,
    split_solved_maps,
    templates_from_terms,
)

log = logging.getLogger(__name__)

SH_TERM = TEMPLATE_TERMS.index("s*h")
SH_TERM_PIECES = ("cmb_h", "noise_h")  # a seed's own part of the s h term
NOISE_REFERENCE_SEED = -1  # the fixed pass's noise realization: a stream no seed (0, 1, ...) uses
SHAPING_BIN_WIDTH = 4  # multipoles averaged in the noise shaping
SHAPING_ITERATIONS = 2  # corrections of the noise shaping for the mask's mode coupling
TRANSFER_SPECTRA = ("tt", "ee", "bb")


def measure_transfer(output_iqu: np.ndarray, input_iqu: np.ndarray, good: np.ndarray, lmax: int):
    """T_ell (3, lmax + 1) for TT, EE, BB: the cross pseudo-spectrum of the filtered-binned
    map with its input over their input pseudo-spectrum, both on the observed pixels
    ``good``; T_ell = 1 where the input has no power (ell < 2 in polarization)."""
    masked_output = np.where(good, output_iqu, 0.0)
    masked_input = np.where(good, input_iqu, 0.0)
    cross = hp.anafast(masked_output, masked_input, lmax=lmax)[:3]
    auto = hp.anafast(masked_input, lmax=lmax)[:3]
    transfer = np.ones_like(auto)
    np.divide(cross, auto, out=transfer, where=auto > 0)
    return transfer


def measure_noise_shaping(filtered_iqu, unfiltered_iqu, good: np.ndarray, lmax: int) -> np.ndarray:
    """S_ell (3, lmax + 1) for TT, EE, BB such that :func:`shaped_noise_map` of the
    unfiltered noise realizations bin n has, summed over them, the pseudo-spectrum of
    the filtered ones, bin F n, on ``good``: starting from sqrt(sum C_ell(bin F n) /
    sum C_ell(bin n)), corrected SHAPING_ITERATIONS times by sqrt(sum C_ell(bin F n) /
    sum C_ell(shaped)) (the mask couples multipoles, so shaping by S does not give S^2
    exactly on a partial sky); averaged over SHAPING_BIN_WIDTH multipoles.
    ``filtered_iqu``, ``unfiltered_iqu``: (3, npix) maps of one realization or
    sequences of them, in the same order."""
    filtered, unfiltered = _realizations(filtered_iqu), _realizations(unfiltered_iqu)

    def summed(maps):
        return sum(_binned_pseudo_spectra(m, good, lmax) for m in maps)

    target = summed(filtered)
    shaping = np.sqrt(_ratio(target, summed(unfiltered)))
    for _ in range(SHAPING_ITERATIONS):
        shaped = [shaped_noise_map(m, shaping, good, lmax) for m in unfiltered]
        shaping *= np.sqrt(_ratio(target, summed(shaped)))
    return shaping


def _realizations(maps) -> list[np.ndarray]:
    """A (3, npix) map or a sequence of them, as a list of (3, npix) maps."""
    maps = np.asarray(maps)
    return [maps] if maps.ndim == 2 else list(maps)


def _binned_pseudo_spectra(maps_iqu: np.ndarray, good: np.ndarray, lmax: int) -> np.ndarray:
    """TT, EE, BB pseudo-spectra on ``good``, summed over SHAPING_BIN_WIDTH multipoles
    (each multipole holds its bin's sum; ell < 2 holds its own value)."""
    spectra = hp.anafast(np.where(good, maps_iqu, 0.0), lmax=lmax)[:3]
    for first in range(2, lmax + 1, SHAPING_BIN_WIDTH):
        window = slice(first, min(first + SHAPING_BIN_WIDTH, lmax + 1))
        spectra[:, window] = spectra[:, window].sum(axis=1, keepdims=True)
    return spectra


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """numerator / denominator, 1 where the denominator is 0 and below ell = 2."""
    ratio = np.ones_like(numerator)
    np.divide(numerator, denominator, out=ratio, where=denominator > 0)
    ratio[:, :2] = 1.0
    return ratio


def shaped_noise_map(noise_iqu: np.ndarray, shaping: np.ndarray, good: np.ndarray, lmax: int):
    """The noise map (zero off ``good``) with its T, E, B a_lm up to lmax times
    ``shaping``: n + alm2map((shaping - 1) a_lm), so the power beyond lmax (white
    pixel noise has it) is kept unshaped. One Jacobi iteration of the analysis above
    lmax = nside, none at or below it (where the quadrature alone is accurate to ~1e-3,
    on a correction that is itself (shaping - 1) of the noise)."""
    nside = hp.npix2nside(good.size)
    masked = np.where(good, noise_iqu, 0.0)
    alm = harmonics.map2alm(masked, lmax, iter=0 if lmax <= nside else 1)
    change = np.array([hp.almxfl(alm[i], shaping[i, : lmax + 1] - 1.0) for i in range(3)])
    return masked + harmonics.alm2map(change, nside, lmax)


def transferred_map(maps_iqu: np.ndarray, transfer: np.ndarray, good: np.ndarray, lmax: int):
    """(3, npix) alm2map(transfer_ell a_lm) of the map (zero off ``good``), band-limited
    to ``lmax`` (nothing kept above it: unlike :func:`shaped_noise_map`, for a map that
    the map-maker does not pass at any ell as the binned one does)."""
    nside = hp.npix2nside(good.size)
    masked = np.where(good, maps_iqu, 0.0)
    alm = harmonics.map2alm(masked, lmax, iter=0 if lmax <= nside else 1)
    alm = np.array([hp.almxfl(alm[i], transfer[i, : lmax + 1]) for i in range(3)])
    return harmonics.alm2map(alm, nside, lmax)


def filtered_cmb_map(
    cmb_iqu: np.ndarray, alm: np.ndarray, transfer: np.ndarray, lmax: int, filter_lmax: int
):
    """(3, npix) map of the a_lm times T_ell per T, E, B up to ``filter_lmax`` [K_CMB]:
    cmb + alm2map((T_ell - 1) a_lm), with ``cmb_iqu`` the map of ``alm`` (band ``lmax``),
    so above ``filter_lmax`` the CMB is kept unfiltered."""
    nside = hp.npix2nside(cmb_iqu.shape[-1])
    band = hp.resize_alm(alm, lmax, lmax, filter_lmax, filter_lmax)
    change = np.array([hp.almxfl(band[i], transfer[i, : filter_lmax + 1] - 1.0) for i in range(3)])
    return cmb_iqu + harmonics.alm2map(change, nside, filter_lmax)


@dataclasses.dataclass
class FixedMaps:
    """Everything the seeds of one channel share (the fixed pass's output)."""

    nosys: np.ndarray  # (3, npix) bin F(s_f + A_2 h) [K_CMB]
    template_terms: np.ndarray  # (3, n_det, 3, npix) terms of s_f [K_CMB^2]
    foreground_reference: np.ndarray  # (3, npix) bin F(fg) [K_CMB]
    transfer: np.ndarray  # (3, measure_lmax + 1) T_ell of TT, EE, BB [1]
    noise_shaping: np.ndarray  # (3, measure_lmax + 1) sqrt(N_ell of F n / N_ell of n) [1]
    noise_h_shaping: np.ndarray  # (3, measure_lmax + 1) the same of h n [1]; (0,) if none
    matrix: np.ndarray  # (6, npix) sum_k M_k, MATRIX_ENTRIES order [K^-2]
    moments: np.ndarray  # (n_det, npix, 3, 6) M_k, H_k, Q_k [K^-2]; (0,) without systematics
    hits: np.ndarray
    condition: np.ndarray
    good: np.ndarray
    carries_systematics: bool
    # (3, measure_lmax + 1) T^h_ell of the seed's CMB part of the s h term, M^-1 H_k CMB,
    # through a demodulated map-maker [1]; (0,): the binned map-maker's, taken unfiltered
    cmb_h_transfer: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    # (3, measure_lmax + 1) S^s_ell, the shaping (as noise_shaping) of the seed's CMB
    # part of the s^2 term by the filter and a demodulated map-maker, from the pixel
    # product of static_sky_product [1]; (0,): left out (the binned map-maker's: 2 % of
    # its s h part)
    cmb_s_shaping: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    # (3, npix) s_f = foreground + dipole, as static_sky_map makes it [K_CMB]; (0,) without S^s
    static_sky: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def matrices(self, pixels) -> np.ndarray:
        """(n, 3, 3) M of the pixels."""
        return symmetric_matrices(self.matrix[:, pixels].T)

    def moment(self, detector: int, weight: int, pixels) -> np.ndarray:
        """(n, 3, 3) M_k (weight 0), H_k (1) or Q_k (2) of a detector at the pixels."""
        return symmetric_matrices(self.moments[detector, pixels, weight])


def fixed_pass(
    simulator,
    settings,
    foreground_iqu_k: np.ndarray,
    transfer_alm: np.ndarray,
    carries_systematics: bool,
    lmax: int,
    calibration_every_chunks: int = 1,
    measure_lmax: int | None = None,
    noise_realizations: int = 1,
    demodulated: bool = False,
) -> FixedMaps:
    """The seed-independent TOD pass of one channel (see the module docstring), binned at
    ``settings.nside`` with ``settings.baseline_length_s``: :func:`fixed_passes` with
    that one map-maker; with ``demodulated`` its demodulated maps (the band-limited sky
    scanned, as the demodulated map-maker needs)."""
    primary = (settings.nside, settings.baseline_length_s)
    passes = fixed_passes(
        simulator,
        settings,
        foreground_iqu_k,
        transfer_alm,
        carries_systematics,
        lmax,
        calibration_every_chunks,
        measure_lmax,
        noise_realizations=noise_realizations,
        demodulated_variants=[primary] if demodulated else (),
        band_limited_sky=demodulated,
    )
    return passes[(*primary, "demodulated")] if demodulated else passes[primary]


def fixed_passes(
    simulator,
    settings,
    foreground_iqu_k: np.ndarray,
    transfer_alm: np.ndarray,
    carries_systematics: bool,
    lmax: int,
    calibration_every_chunks: int = 1,
    measure_lmax: int | None = None,
    extra_variants=(),
    noise_realizations: int = 1,
    demodulated_variants=(),
    band_limited_sky: bool = False,
) -> dict[tuple, FixedMaps]:
    """{(nside, baseline length): FixedMaps} of the seed-independent TOD pass of one
    channel (see the module docstring): no CMB, no noise; the sky (``foreground_iqu_k``,
    and ``transfer_alm``, beam-smoothed, band ``lmax``, scanned alone to measure T_ell)
    scanned at ``settings.nside``, and ``noise_realizations`` reference noise
    realizations giving S_ell and S^h_ell, both on every ``calibration_every_chunks``-th
    chunk (:class:`tod_maps.Calibration`). The TODs are binned at (settings.nside, settings.baseline_length_s) and at every
    (nside, baseline length) of ``extra_variants`` in the same pass
    (:class:`tod_maps.ExtraBinning`): the binning is cheap beside the TOD. T_ell and
    S_ell are measured up to ``measure_lmax`` (default ``lmax``; at most 3 nside - 1 of
    each variant): the seeds apply them up to ``simulation.filter_lmax`` only, so
    measuring beyond it (full-band spherical transforms, most of a pass's fixed cost at
    nside 512) buys nothing. ``demodulated_variants``: (nside, baseline length) of
    HWP-demodulating map-makers (:class:`tod_maps.ExtraBinning` with ``demodulated``;
    each needs a binned variant of its resolution), keyed (nside, baseline length,
    "demodulated"). ``band_limited_sky``: the foreground and the reference CMB scanned
    as a_lm (:class:`sky.harmonics.BandLimitedSky`) rather than at the nearest pixel."""
    measure_lmax = lmax if measure_lmax is None else measure_lmax
    if not 0 < measure_lmax <= lmax:
        raise ValueError(f"measure_lmax = {measure_lmax} must be in 1..lmax = {lmax}")
    primary = (settings.nside, settings.baseline_length_s)
    extra_variants = [tuple(v) for v in extra_variants if tuple(v) != primary]
    if any(nside > settings.nside for nside, _ in extra_variants):
        raise ValueError(
            f"fixed pass variants {extra_variants}: the sky is scanned at nside "
            f"{settings.nside}, so no variant may be finer"
        )
    transfer_input = hp.alm2map(transfer_alm, settings.nside, lmax=lmax, pixwin=False)
    n_det = simulator.n_detectors
    nsides = {settings.nside} | {nside for nside, _ in extra_variants}
    moments_of = {n: PixelMoments(n, n_det) if carries_systematics else None for n in nsides}
    extras = [
        ExtraBinning(nside, baseline, moments=moments_of[nside])
        for nside, baseline in extra_variants
    ]
    demodulated = [
        ExtraBinning(nside, baseline, moments=moments_of.get(nside), demodulated=True)
        for nside, baseline in (tuple(v) for v in demodulated_variants)
    ]
    if any(e.moments is None and carries_systematics for e in demodulated):
        raise ValueError(
            f"demodulated variants {list(demodulated_variants)}: each needs a binned variant "
            "of its resolution in the pass (their HWPSS moments are shared)"
        )
    noiseless = dataclasses.replace(settings, noise_scale=0.0)
    scanned_foreground, scanned_reference = foreground_iqu_k, transfer_input
    if band_limited_sky:
        threads = settings.threads
        scanned_foreground = BandLimitedSky.from_map(foreground_iqu_k, lmax, threads)
        scanned_reference = BandLimitedSky(transfer_alm, lmax, threads)
    calibration = Calibration(
        settings.nside,
        (scanned_reference,),
        NOISE_REFERENCE_SEED,
        calibration_every_chunks,
        hwpss_noise=carries_systematics,
        noise_realizations=noise_realizations,
        template_references=carries_systematics and bool(demodulated),
    )
    equations = accumulate(
        simulator,
        noiseless,
        scanned_foreground,
        references_iqu_k=(scanned_foreground,),
        template_terms=carries_systematics,
        moments=moments_of[settings.nside],
        calibration=calibration,
        extra_binnings=tuple(extras + demodulated),
    )
    static_sky = None
    if calibration.static_sky is not None:
        static_sky = static_sky_map(calibration.static_sky, foreground_iqu_k)
    binned = [(primary, equations, calibration.equations, moments_of[settings.nside])]
    binned += [
        ((e.nside, e.baseline_length_s), e.equations, e.calibration_equations, e.moments)
        for e in extras
    ]

    def reference_at(nside):
        """(the reference CMB map at a map-maker's resolution, its band)."""
        band = min(lmax, 3 * nside - 1)
        if nside == settings.nside:
            return transfer_input, band
        alm = hp.resize_alm(transfer_alm, lmax, lmax, band, band)
        return hp.alm2map(alm, nside, lmax=band, pixwin=False), band

    results = {}
    for (nside, baseline), variant_equations, calibration_equations, moments in binned:
        reference, band = reference_at(nside)
        results[(nside, baseline)] = _solve_fixed_pass(
            simulator,
            settings,
            variant_equations,
            calibration_equations,
            moments,
            reference,
            carries_systematics,
            min(measure_lmax, band),
            calibration,
        )
        log.info("fixed pass variant nside %d, baselines %s: solved", nside, baseline)
    for extra in demodulated:
        reference, band = reference_at(extra.nside)
        results[(extra.nside, extra.baseline_length_s, "demodulated")] = _solve_demodulated(
            simulator,
            settings,
            extra,
            reference,
            carries_systematics,
            min(measure_lmax, band),
            calibration,
            static_sky,
        )
        log.info(
            "fixed pass variant nside %d, baselines %s, demodulated: solved",
            extra.nside,
            extra.baseline_length_s,
        )
    return results


def _solve_demodulated(
    simulator,
    settings,
    extra,
    transfer_input,
    carries_systematics,
    measure_lmax,
    calibration,
    static_sky,
) -> FixedMaps:
    """FixedMaps of a demodulated map-maker (:class:`tod_maps.ExtraBinning` with
    ``demodulated``): its maps; good where it has samples and the binned solve's M (the
    white noise the seeds draw, :class:`BinnedNoise`) is well conditioned; T_ell of the
    reference CMB through the filter and the demodulation; S_ell and S^h_ell of its
    filtered, demodulated noise maps against the same noise binned unfiltered; with
    systematics T^h_ell, the demodulated h x CMB reference against the binned map-maker's
    M^-1 sum_k H_k CMB (:func:`hwpss_cmb_map`), which the seeds' CMB piece of the s h term
    is made as, and S^s_ell, the demodulated 2 s_f x CMB reference's shaping from the pixel
    product of ``static_sky`` (:func:`static_sky_map` at the pass's resolution, None
    without template references; here degraded to the map-maker's) and the reference
    (:func:`static_sky_product`), which the seeds' CMB piece of the s^2 term is made as."""
    _, condition, binned_good = solve_maps(extra.matrix_equations, settings.max_condition_number)
    good = binned_good & (extra.equations.hits > 0)
    maps = extra.equations.solve()
    maps[:, :, ~good] = hp.UNSEEN
    solved = extra.calibration_equations.solve()
    transfer_output, filtered = solved[0], solved[calibration.n_reference_tods :]
    unfiltered, _, white_good = solve_maps(extra.white_equations, settings.max_condition_number)
    calibrated = white_good & (extra.calibration_equations.hits > 0)
    fixed = _fixed_maps(
        simulator,
        settings,
        (maps, condition, good),
        extra.matrix_equations.matrix,
        extra.matrix_equations.hits,  # every sample's, as the binned map-maker's (the
        # demodulated streams are binned at every D-th: tod_maps._demodulated_streams)
        (transfer_output, np.asarray(filtered), unfiltered, calibrated),
        extra.moments,
        transfer_input,
        carries_systematics,
        measure_lmax,
        calibration.kinds,
    )
    if calibration.template_references:
        scanned = len(calibration.references_iqu_k)
        binned = hwpss_cmb_map(fixed, transfer_input)
        fixed.cmb_h_transfer = measure_transfer(solved[scanned], binned, calibrated, measure_lmax)
        static = hp.ud_grade(static_sky, extra.nside)  # averages the solved sub-pixels
        fixed.static_sky = np.where(static == hp.UNSEEN, 0.0, static)
        product = static_sky_product(fixed.static_sky, transfer_input)
        fixed.cmb_s_shaping = measure_noise_shaping(
            solved[2 * scanned], product, calibrated, measure_lmax
        )
    return fixed


def static_sky_map(binned, foreground_iqu_k: np.ndarray) -> np.ndarray:
    """(3, npix) s_f as its pixel products need it [K_CMB]: I the pixel's weighted mean of
    the TOD s_f = foreground + dipole (``binned``: its NormalEquations, unfiltered; the
    dipole changes with the orbit), Q and U the foreground map's (the dipole has none; a
    binned solve's Q, U would carry the intensity's sub-pixel gradients, measured 6x the
    foreground's at nside 32); UNSEEN where no sample fell."""
    weight = binned.matrix[MATRIX_ENTRIES.index((0, 0))]
    seen = binned.hits > 0
    static = np.array(foreground_iqu_k, dtype=float)
    static[0] = np.where(seen, binned.rhs[0, 0] / np.where(seen, weight, 1.0), hp.UNSEEN)
    static[1:, ~seen] = hp.UNSEEN
    return static


def demodulated_shares(fixed: FixedMaps, pixels) -> np.ndarray:
    """(n_det, 3, n) detector k's share of a demodulated map of a sky signal at the pixels
    [1]: sum_k w / sum w for I, sum_k w rho^2 / sum w rho^2 for Q and U (the demodulated
    map-maker's per-pixel averages, :mod:`demodulation`), read from M_k and M (their
    I-I entry and the trace of their Q/U block)."""
    ii, qq, uu = (MATRIX_ENTRIES.index(entry) for entry in ((0, 0), (1, 1), (2, 2)))
    moments = fixed.moments[:, pixels, 0]  # (n_det, n, 6) M_k
    total = fixed.matrix[:, pixels]  # (6, n) M
    share_i = moments[..., ii] / total[ii]
    share_p = (moments[..., qq] + moments[..., uu]) / (total[qq] + total[uu])
    return np.stack([share_i, share_p, share_p], axis=1)


def static_sky_product(static_iqu: np.ndarray, cmb_iqu: np.ndarray) -> np.ndarray:
    """(3, npix) the map a map-maker makes of 2 s_f x when s_f and x are constant in a
    pixel and its HWP angles are uniform [K_CMB^2]: with s = I + rho (Q cos 4 chi' + U sin
    4 chi') (chi' the HWP angle in the sky frame), the product's parts at 0 and 4 chi':
    I = 2 I_f I_x + rho^2 (Q_f Q_x + U_f U_x), Q = 2 (I_f Q_x + I_x Q_f), U = 2 (I_f U_x
    + I_x U_f), here with rho^2 = 1 (the measured S^s_ell carries the rest; the 8 chi'
    part is lost to the binning)."""
    i_f, q_f, u_f = static_iqu
    i_x, q_x, u_x = cmb_iqu
    return np.array(
        [
            2.0 * i_f * i_x + q_f * q_x + u_f * u_x,
            2.0 * (i_f * q_x + i_x * q_f),
            2.0 * (i_f * u_x + i_x * u_f),
        ]
    )


def hwpss_cmb_map(fixed: FixedMaps, cmb_iqu: np.ndarray) -> np.ndarray:
    """(3, npix) M^-1 sum_k H_k CMB on the good pixels (zero elsewhere) [K_CMB]: the binned
    map of the CMB times the unit HWPSS of every detector (its part of the s h term)."""
    good = np.flatnonzero(fixed.good)
    summed = sum(
        np.einsum("pij,jp->ip", fixed.moment(k, 1, good), cmb_iqu[:, good])
        for k in range(fixed.moments.shape[0])
    )
    binned = np.zeros_like(cmb_iqu)
    binned[:, good] = np.einsum("pij,jp->ip", np.linalg.inv(fixed.matrices(good)), summed)
    return binned


def _solve_fixed_pass(
    simulator,
    settings,
    equations,
    calibration_equations,
    moments,
    transfer_input,
    carries_systematics: bool,
    measure_lmax: int,
    calibration,
) -> FixedMaps:
    """FixedMaps of one map-maker's accumulated equations: the maps solved, T_ell and
    S_ell (and S^h_ell) measured up to ``measure_lmax`` against the reference CMB
    ``transfer_input`` at the map-maker's resolution; ``calibration``: the pass's
    :class:`tod_maps.Calibration` (its reference TODs, then per realization n and, with
    systematics, h n: :attr:`~tod_maps.Calibration.kinds`)."""
    solution = solve_maps(equations, settings.max_condition_number)
    calibration_maps, _, calibrated = solve_maps(
        calibration_equations, settings.max_condition_number
    )
    transfer_output = calibration_maps[0]
    noise_maps = calibration_maps[calibration.n_reference_tods :]
    # per realization n and, with systematics, h n (``kinds``); all filtered, then unfiltered
    filtered, unfiltered = np.split(np.asarray(noise_maps), 2)
    return _fixed_maps(
        simulator,
        settings,
        solution,
        equations.matrix,
        equations.hits,
        (transfer_output, filtered, unfiltered, calibrated),
        moments,
        transfer_input,
        carries_systematics,
        measure_lmax,
        calibration.kinds,
    )


def _fixed_maps(
    simulator,
    settings,
    solution,
    matrix,
    hits,
    calibration,
    moments,
    transfer_input,
    carries_systematics: bool,
    measure_lmax: int,
    kinds: int,
) -> FixedMaps:
    """FixedMaps from a map-maker's solution (maps (n_tods, 3, npix), condition, good),
    the binned solve's M and hits, and its calibration maps (the filtered reference CMB,
    the filtered noise maps, the same noise binned unfiltered, the calibrated pixels):
    T_ell against ``transfer_input``, S_ell per noise kind (``kinds``), up to
    ``measure_lmax``."""
    maps, condition, good = solution
    transfer_output, filtered, unfiltered, calibrated = calibration
    solved = split_solved_maps(
        maps, simulator.n_detectors, settings.a2_k_cmb, template_terms=carries_systematics
    )
    (foreground_reference,) = solved["references"]
    shapings = [
        measure_noise_shaping(
            filtered[kind::kinds], unfiltered[kind::kinds], calibrated, measure_lmax
        )
        for kind in range(kinds)
    ]
    return FixedMaps(
        nosys=solved["nosys"],
        template_terms=solved["template_terms"],
        foreground_reference=foreground_reference,
        transfer=measure_transfer(transfer_output, transfer_input, calibrated, measure_lmax),
        noise_shaping=shapings[0],
        noise_h_shaping=shapings[1] if kinds == 2 else np.zeros(0),
        matrix=matrix,
        moments=moments.values if carries_systematics else np.zeros(0),
        hits=hits,
        condition=condition,
        good=good,
        carries_systematics=carries_systematics,
    )


class BinnedNoise:
    """The binned white noise of a channel's fixed pass, drawn seed after seed: (b, c) with
    b (3, npix) = sum_k b_k and c (n_det, 3, npix) the binned h n per detector, on the good
    pixels (zero elsewhere). Each 6-vector (b_k, c_k) is drawn from the eigenvectors of
    its covariance noise_scale^2 [[M_k, H_k], [H_k, Q_k]] (negative rounding eigenvalues
    set to 0): the per-pixel eigendecompositions depend on the fixed pass only, so they
    are computed once here and every seed costs one matrix-vector product per pixel. A
    channel without systematics has no moments: b is drawn from noise_scale^2 M with
    detector 0's generator, and c is empty."""

    def __init__(self, fixed: FixedMaps, noise_scale: float):
        self.good = np.flatnonzero(fixed.good)
        self.npix = fixed.good.size
        self.carries_systematics = fixed.carries_systematics
        if not fixed.carries_systematics:
            self.factors = [_eigen_factor(noise_scale**2 * fixed.matrices(self.good))]
            return
        self.factors = []
        for k in range(fixed.moments.shape[0]):
            m_k, h_k, q_k = (fixed.moment(k, j, self.good) for j in range(3))
            covariance = np.block([[m_k, h_k], [h_k, q_k]]) * noise_scale**2
            self.factors.append(_eigen_factor(covariance))

    def draw(self, rng_of_detector) -> tuple[np.ndarray, np.ndarray]:
        """(b, c) of one seed; ``rng_of_detector(k)`` gives detector k's generator."""
        b = np.zeros((3, self.npix))
        if not self.carries_systematics:
            b[:, self.good] = _gaussian(self.factors[0], rng_of_detector(0)).T
            return b, np.zeros((0, 3, self.npix))
        c = np.zeros((len(self.factors), 3, self.npix))
        for k, factor in enumerate(self.factors):
            draw = _gaussian(factor, rng_of_detector(k))
            b[:, self.good] += draw[:, :3].T
            c[k][:, self.good] = draw[:, 3:].T
        return b, c


class SeedOperators:
    """What every seed of a channel applies, computed once from its fixed pass: the binned
    noise's factors (:class:`BinnedNoise`), M^-1 and the H_k of the good pixels, and the
    last multipole ``filter_lmax`` to which the filter's action (T_ell on the CMB, S_ell on
    the noise) is applied: the analysis reads no higher (component_separation lmax), and
    filtering beyond it costs transforms at the map's full band for nothing it uses."""

    def __init__(self, fixed: FixedMaps, noise_scale: float, filter_lmax: int):
        good = np.flatnonzero(fixed.good)
        self.noise = BinnedNoise(fixed, noise_scale)
        self.inverse = np.linalg.inv(fixed.matrices(good))  # (n_good, 3, 3) M^-1 [K^2]
        n_det = fixed.moments.shape[0] if fixed.carries_systematics else 0
        self.h_matrices = [fixed.moment(k, 1, good) for k in range(n_det)]  # H_k [K^-2]
        # (n_det, 3, n_good) the detectors' shares of a demodulated map [1], for the s^2
        # term's CMB part (if modelled)
        self.demodulated_shares = (
            demodulated_shares(fixed, good) if fixed.cmb_s_shaping.size else np.zeros(0)
        )
        self.filter_lmax = filter_lmax

    def solve(self, vectors: np.ndarray) -> np.ndarray:
        """M^-1 v on the good pixels: (3, n_good) -> (3, n_good)."""
        return np.einsum("pij,jp->ip", self.inverse, vectors)


def _eigen_factor(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvectors (n, d, d), sqrt of the eigenvalues clipped at 0 (n, d)) of (n, d, d)."""
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    return eigenvectors, np.sqrt(np.clip(eigenvalues, 0, None))


def _gaussian(factor: tuple[np.ndarray, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """(n, d) draws x = V sqrt(lambda) z, z ~ N(0, 1), with (V, sqrt(lambda)) = ``factor``."""
    eigenvectors, root_eigenvalues = factor
    z = rng.standard_normal(root_eigenvalues.shape)
    return np.einsum("pij,pj->pi", eigenvectors, root_eigenvalues * z)


def realize_seed(
    fixed: FixedMaps,
    cmb_alm: np.ndarray,
    lmax: int,
    a2_k_cmb: float,
    noise_scale: float,
    rng_of_detector,
    operators: SeedOperators | None = None,
    full_terms: bool = True,
) -> dict[str, np.ndarray]:
    """The maps of one seed from the fixed pass (see the module docstring): nosys,
    template_terms, templates, cmb_reference, foreground_reference (UNSEEN where the
    fixed pass is not good), as :func:`tod_maps.split_solved_maps` names them,
    cmb_input, the seed's CMB map before the filter (the map of ``cmb_alm``, everywhere),
    and the seed's two pieces of the s h term, ``sh_term_pieces`` {"cmb_h", "noise_h"}:
    (n_det, 3, npix) each, zero off the good pixels (the s h term is the fixed pass's
    plus these). Where the fixed pass measured S^s (a demodulated map-maker), "cmb_h"
    also carries the seed's CMB part of the s^2 term, detector k's share
    (:func:`demodulated_shares`) of S^s P(s_f, CMB) with P of
    :func:`static_sky_product`, divided by 2 A_2 (the s h term's coefficient in the
    template): the template is the same, and its seed part stays in two pieces.
    ``operators``: the :class:`SeedOperators` of (fixed, noise_scale), shared by the seeds
    of a channel (built here, filtering up to ``lmax``, if None). ``full_terms`` False
    leaves out template_terms and templates (the fixed pass's terms plus the pieces: the
    seeds' a_lm take the fixed part's once, :func:`ilc_residuals.fixed_term_alms`)."""
    nside = hp.npix2nside(fixed.good.size)
    good = fixed.good
    operators = operators or SeedOperators(fixed, noise_scale, lmax)
    cmb = harmonics.alm2map(cmb_alm, nside, lmax)
    cmb_filtered = filtered_cmb_map(cmb, cmb_alm, fixed.transfer, lmax, operators.filter_lmax)
    b, c = operators.noise.draw(rng_of_detector)

    def filtered_noise(vectors, shaping):  # the binned white noise, shaped by the filter
        white = np.zeros_like(fixed.nosys)
        white[:, good] = operators.solve(vectors)
        shaped = shaped_noise_map(white, shaping, good, operators.filter_lmax)
        return shaped[:, good]

    noise = np.zeros_like(fixed.nosys)
    noise[:, good] = filtered_noise(b[:, good], fixed.noise_shaping)
    nosys = np.full_like(fixed.nosys, hp.UNSEEN)
    nosys[:, good] = fixed.nosys[:, good] + cmb_filtered[:, good] + noise[:, good]
    pieces = {name: np.zeros_like(fixed.template_terms[SH_TERM]) for name in SH_TERM_PIECES}
    for k, h_k in enumerate(operators.h_matrices):  # the s h term gets the seed's part
        cmb_h = operators.solve(np.einsum("pij,jp->ip", h_k, cmb[:, good]))
        if fixed.cmb_h_transfer.size:  # a demodulated map-maker: as the fixed pass measured
            binned = np.zeros_like(fixed.nosys)
            binned[:, good] = cmb_h
            cmb_h = transferred_map(binned, fixed.cmb_h_transfer, good, operators.filter_lmax)
            cmb_h = cmb_h[:, good]
        pieces["cmb_h"][k][:, good] = cmb_h
        pieces["noise_h"][k][:, good] = filtered_noise(c[k][:, good], fixed.noise_h_shaping)
    if operators.demodulated_shares.size and a2_k_cmb:  # the s^2 term's CMB part, in s h units
        product = static_sky_product(fixed.static_sky, cmb)
        # shaped by S^s up to filter_lmax, kept as it is above (as the noise by S)
        product = shaped_noise_map(product, fixed.cmb_s_shaping, good, operators.filter_lmax)
        for k, share in enumerate(operators.demodulated_shares):
            pieces["cmb_h"][k][:, good] += share * product[:, good] / (2.0 * a2_k_cmb)
    maps = {
        "nosys": nosys,
        "cmb_reference": np.where(good, cmb_filtered, hp.UNSEEN),
        "foreground_reference": fixed.foreground_reference,
        "cmb_input": cmb,
        "sh_term_pieces": pieces,
    }
    if full_terms:
        terms = fixed.template_terms.copy()
        terms[SH_TERM] += pieces["cmb_h"] + pieces["noise_h"]
        maps["template_terms"] = terms
        maps["templates"] = np.where(good, templates_from_terms(terms, a2_k_cmb), hp.UNSEEN)
    return maps


class ChannelSeeds:
    """The seeds of one channel made from its fixed pass file: :meth:`maps` of a seed as
    the TOD path's maps file holds them (nosys, template_terms, templates, cmb_reference,
    foreground_reference, attrs), each seed's CMB the draw of
    :func:`sky.cmb.band_limited_seed_cmb` and its noise the stream ("map-domain noise", channel,
    seed, detector); the filter's action applied up to ``simulation.filter_lmax`` (at
    most the map's band 3 nside - 1). The operators are computed once, on the first seed.
    ``pooled_h5s``: the fixed passes whose noise shaping is pooled with this one's
    (:func:`config.noise_shaping_siblings`; this channel's file among them): the seeds then use
    :func:`pooled_noise_shaping` of them."""

    def __init__(self, config: dict, fixed_h5, pooled_h5s=()):
        self.config = config
        self.fixed, self.attributes = read_fixed_maps(fixed_h5)
        if len(pooled_h5s) > 1:  # siblings share the systematics: S^h pools like S
            shaping, h_shaping = pooled_noise_shaping(pooled_h5s)
            self.fixed = dataclasses.replace(
                self.fixed, noise_shaping=shaping, noise_h_shaping=h_shaping
            )
        self.name = str(self.attributes["channel"])
        self.fwhm_arcmin = cfg.channel(config, self.name).fwhm_arcmin
        self.lmax = 3 * int(self.attributes["nside"]) - 1
        measured = self.fixed.transfer.shape[1] - 1
        self.filter_lmax = min(config["simulation"]["filter_lmax"] or self.lmax, self.lmax)
        if measured < self.filter_lmax:
            raise ValueError(
                f"{fixed_h5}: the fixed pass measured the filter up to ell = {measured}, but "
                f"simulation.filter_lmax asks for {self.filter_lmax}: rerun its fixed_pass rule"
            )
        self._operators = None

    @classmethod
    def from_run(cls, config: dict, fixed_h5) -> ChannelSeeds:
        """As the workflow makes them: the noise shaping pooled over the fixed passes of
        :func:`config.noise_shaping_siblings` in the same run folder (``<maps>/<channel>/<the
        same file name>``; those not made are left out, with a warning)."""
        fixed_h5 = Path(fixed_h5)
        name = read_fixed_attribute(fixed_h5, "channel")
        pooled = []
        for sibling in cfg.noise_shaping_siblings(config, name):
            path = fixed_h5.parent.parent / sibling / fixed_h5.name
            if path.exists():
                pooled.append(path)
            else:
                log.warning("%s: no fixed pass %s to pool its noise shaping with", name, path)
        return cls(config, fixed_h5, pooled)

    @property
    def operators(self) -> SeedOperators:
        """The :class:`SeedOperators` the seeds share (built on first use)."""
        if self._operators is None:
            noise_scale = self.config["simulation"]["noise_scale"]
            self._operators = SeedOperators(self.fixed, noise_scale, self.filter_lmax)
        return self._operators

    @property
    def fixed_templates(self) -> np.ndarray:
        """(n_det, 3, npix) the fixed pass's templates T_k at the channel's A_2 [K_CMB^2],
        zero off its good pixels: a seed's templates minus these are its seed part."""
        a2_k_cmb = float(self.attributes["a2_k_cmb"])
        terms = self.fixed.template_terms
        return np.where(self.fixed.good, templates_from_terms(terms, a2_k_cmb), 0.0)

    def noise_generator(self, seed: int):
        """rng_of_detector(k) of a seed: detector k's stream ("map-domain noise", channel,
        seed, detector)."""
        detectors = list(self.attributes["detectors"])
        master_seed = self.config["master_seed"]

        def rng_of_detector(k):
            return seeding.rng(master_seed, "map-domain noise", self.name, seed, detectors[k])

        return rng_of_detector

    def maps(self, seed: int, full_terms: bool = True) -> dict:
        """The maps of ``seed`` (:func:`realize_seed`; ``full_terms`` passed on)."""
        simulation, master_seed = self.config["simulation"], self.config["master_seed"]
        cmb_alm, band = sky_cmb.band_limited_seed_cmb(
            self.lmax, simulation["cmb_r"], master_seed, seed, self.fwhm_arcmin
        )
        maps = realize_seed(
            self.fixed,
            cmb_alm,
            band,
            float(self.attributes["a2_k_cmb"]),
            simulation["noise_scale"],
            self.noise_generator(seed),
            self.operators,
            full_terms,
        )
        maps["attrs"] = {**self.attributes, "seed": seed, "realization": "map_domain"}
        return maps


def pooled_noise_shaping(fixed_h5s) -> tuple[np.ndarray, np.ndarray]:
    """(S_ell, S^h_ell) pooled over fixed passes whose shaping is the same by construction
    (:func:`config.noise_shaping_siblings`): S = sqrt(sum_c K_c S_c^2 / sum_c K_c), K_c the
    noise reference realizations of file c (its ``noise_reference_realizations``
    attribute, 1 if absent). Each S_c^2 is a ratio of pseudo-spectra summed over its
    realizations, so the pooled one averages sum_c K_c of them: its scatter at low ell
    (a realization's S^2 differs by 30 % to 3x at ell 2-11) falls as 1 / sqrt(sum K_c).
    S^h pools the files that carry systematics; (0,) if none does."""
    if not fixed_h5s:
        raise ValueError("pooled_noise_shaping: no fixed pass files given")
    sums = {"noise_shaping": [0.0, 0.0], "noise_h_shaping": [0.0, 0.0]}
    shape = None
    for path in fixed_h5s:
        with h5py.File(path) as stored:
            weight = float(stored.attrs.get("noise_reference_realizations", 1))
            for name, total in sums.items():
                if name not in stored or stored[name].size == 0:
                    continue
                values = stored[name][()]
                shape = shape or values.shape
                if values.shape != shape:
                    raise ValueError(
                        f"{path}: {name} of shape {values.shape}, the other pooled fixed "
                        f"passes' {shape} (measured to another ell): rerun its fixed_pass rule"
                    )
                total[0] += weight * values**2
                total[1] += weight
    pooled = [
        np.sqrt(total / weight) if weight else np.zeros(0)
        for total, weight in (sums["noise_shaping"], sums["noise_h_shaping"])
    ]
    return pooled[0], pooled[1]


def write_fixed_maps(path, fixed: FixedMaps, attributes: dict, moments_in=None) -> None:
    """The fixed pass of one channel as HDF5 (datasets named as FixedMaps' fields). A
    channel without systematics stores no template terms (all zero) and no moments;
    ``moments_in``: the file name, in the same folder, that holds the HWPSS moments (the
    map-makers of one resolution share them: at nside 512 they are 0.9 GB a channel)."""
    skipped = set() if fixed.carries_systematics else {"template_terms", "moments"}
    if moments_in is not None:
        skipped.add("moments")
    with atomic_path(path) as temporary, h5py.File(temporary, "w") as out:
        for field in dataclasses.fields(FixedMaps):
            value = getattr(fixed, field.name)
            if isinstance(value, np.ndarray) and field.name not in skipped:
                out.create_dataset(field.name, data=value)
        out.attrs.update(attributes)
        out.attrs["carries_systematics"] = fixed.carries_systematics
        if moments_in is not None:
            out.attrs["moments_in"] = str(moments_in)


def read_fixed_field(path, name: str) -> np.ndarray:
    """One dataset of a fixed pass file (e.g. ``good``), without reading the rest."""
    with h5py.File(path) as stored:
        return stored[name][()]


def read_fixed_attribute(path, name: str):
    """One attribute of a fixed pass file (e.g. ``channel``)."""
    with h5py.File(path) as stored:
        value = stored.attrs[name]
    return value.decode() if isinstance(value, bytes) else value


def moments_file(path) -> Path | None:
    """The file that holds the HWPSS moments of a fixed pass file, if another one."""
    with h5py.File(path) as stored:
        name = stored.attrs.get("moments_in")
    return None if name is None else Path(path).parent / str(name)


def read_fixed_maps(path) -> tuple[FixedMaps, dict]:
    """(FixedMaps, attributes) of a file written by :func:`write_fixed_maps`."""
    with h5py.File(path) as stored:
        attributes = dict(stored.attrs)
        arrays = {
            field.name: stored[field.name][()]
            for field in dataclasses.fields(FixedMaps)
            if field.name in stored
        }
    carries = bool(attributes.pop("carries_systematics"))
    holder = moments_file(path)
    attributes.pop("moments_in", None)
    if carries and holder is not None:
        arrays["moments"] = read_fixed_field(holder, "moments")
    if "noise_h_shaping" not in arrays:
        if carries:
            raise ValueError(
                f"{path}: a fixed pass written before the filter's action on the s h term's "
                "noise (noise_h_shaping) was measured; make it again: snakemake --forcerun "
                "fixed_pass"
            )
        arrays["noise_h_shaping"] = np.zeros(0)
    if not carries:
        n_det = len(attributes["detectors"])
        arrays["template_terms"] = np.zeros((len(TEMPLATE_TERMS), n_det, *arrays["nosys"].shape))
        arrays["moments"] = np.zeros(0)
    return FixedMaps(**arrays, carries_systematics=carries), attributes
