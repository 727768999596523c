"""The fixed pass of the map-domain path: one seed-independent TOD pass per channel
(foregrounds, dipole, HWPSS; no CMB, no noise) through the filters and every map-maker of
the run, its binned maps, template terms, HWPSS moments and the filter's measured
response (:mod:`filter_response`), and its file. The method, and what it approximates,
is in :mod:`map_domain`.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import h5py
import healpy as hp
import numpy as np

from ..io import atomic_path
from ..sky.harmonics import BandLimitedSky
from .chunk_binning import ExtraBinning
from .filter_response import (
    b_modes_alone,
    measure_cmb_response,
    measure_noise_shaping,
    measure_transfer,
)
from .mapmaking import MATRIX_ENTRIES, PixelMoments, solve_maps, symmetric_matrices
from .tod_maps import TEMPLATE_TERMS, Calibration, accumulate, split_solved_maps

log = logging.getLogger(__name__)

NOISE_REFERENCE_SEED = -1  # the fixed pass's noise realization: a stream no seed (0, 1, ...) uses


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
    # (2, measure_lmax + 1) E_ell, the BB the filtered map holds beyond T_ell a_lm over the
    # reference's BB, from its B modes and from its T and E modes
    # (filter_response.measure_excess_bb) [1]; (0,): not measured (the seeds add none)
    cmb_bb_excess: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

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
    scanned at ``settings.nside``, its B modes alone beside it to measure the BB excess
    :func:`filter_response.measure_excess_bb`, and ``noise_realizations`` reference noise
    realizations giving S_ell and S^h_ell, both on every ``calibration_every_chunks``-th
    chunk (:class:`tod_maps.Calibration`). The TODs are binned at (settings.nside, settings.baseline_length_s) and at every
    (nside, baseline length) of ``extra_variants`` in the same pass
    (:class:`chunk_binning.ExtraBinning`): the binning is cheap beside the TOD. T_ell and
    S_ell are measured up to ``measure_lmax`` (default ``lmax``; at most 3 nside - 1 of
    each variant): the seeds apply them up to ``simulation.filter_lmax`` only, so
    measuring beyond it (full-band spherical transforms, most of a pass's fixed cost at
    nside 512) buys nothing. ``demodulated_variants``: (nside, baseline length) of
    HWP-demodulating map-makers (:class:`chunk_binning.ExtraBinning` with ``demodulated``;
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
    transfer_alm = np.asarray(transfer_alm)
    transfer_input = hp.alm2map(transfer_alm, settings.nside, lmax=lmax, pixwin=False)
    b_alm = b_modes_alone(transfer_alm)
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
    if band_limited_sky:
        threads = settings.threads
        scanned_foreground = BandLimitedSky.from_map(foreground_iqu_k, lmax, threads)
        scanned_references = tuple(BandLimitedSky(a, lmax, threads) for a in (transfer_alm, b_alm))
    else:
        b_input = hp.alm2map(b_alm, settings.nside, lmax=lmax, pixwin=False)
        scanned_foreground, scanned_references = foreground_iqu_k, (transfer_input, b_input)
    calibration = Calibration(
        settings.nside,
        scanned_references,
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
        """((the reference CMB map at a map-maker's resolution, its a_lm), their band)."""
        band = min(lmax, 3 * nside - 1)
        if nside == settings.nside:
            return (transfer_input, transfer_alm), band
        alm = np.asarray(hp.resize_alm(transfer_alm, lmax, lmax, band, band))
        return (hp.alm2map(alm, nside, lmax=band, pixwin=False), alm), band

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
    """FixedMaps of a demodulated map-maker (:class:`chunk_binning.ExtraBinning` with
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
    transfer_outputs, filtered = solved[:2], solved[calibration.n_reference_tods :]
    unfiltered, _, white_good = solve_maps(extra.white_equations, settings.max_condition_number)
    calibrated = white_good & (extra.calibration_equations.hits > 0)
    fixed = _fixed_maps(
        simulator,
        settings,
        (maps, condition, good),
        extra.matrix_equations.matrix,
        extra.matrix_equations.hits,  # every sample's, as the binned map-maker's (the
        # demodulated streams are binned at every D-th: chunk_binning.demodulated_streams)
        (transfer_outputs, np.asarray(filtered), unfiltered, calibrated),
        extra.moments,
        transfer_input,
        carries_systematics,
        measure_lmax,
        calibration.kinds,
    )
    if calibration.template_references:
        scanned = len(calibration.references_iqu_k)
        binned = hwpss_cmb_map(fixed, transfer_input[0])
        fixed.cmb_h_transfer = measure_transfer(solved[scanned], binned, calibrated, measure_lmax)
        static = hp.ud_grade(static_sky, extra.nside)  # averages the solved sub-pixels
        fixed.static_sky = np.where(static == hp.UNSEEN, 0.0, static)
        product = static_sky_product(fixed.static_sky, transfer_input[0])
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
    transfer_outputs = calibration_maps[:2]  # the reference, its B modes alone
    noise_maps = calibration_maps[calibration.n_reference_tods :]
    # per realization n and, with systematics, h n (``kinds``); all filtered, then unfiltered
    filtered, unfiltered = np.split(np.asarray(noise_maps), 2)
    return _fixed_maps(
        simulator,
        settings,
        solution,
        equations.matrix,
        equations.hits,
        (transfer_outputs, filtered, unfiltered, calibrated),
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
    the binned solve's M and hits, and its calibration maps (the filtered reference CMB
    and its B modes alone, the filtered noise maps, the same noise binned unfiltered, the
    calibrated pixels): T_ell against ``transfer_input`` (the reference's map and a_lm),
    the BB excess, S_ell per noise kind (``kinds``), up to ``measure_lmax``."""
    maps, condition, good = solution
    transfer_outputs, filtered, unfiltered, calibrated = calibration
    reference_map, reference_alm = transfer_input
    transfer, excess = measure_cmb_response(
        transfer_outputs, reference_map, reference_alm, calibrated, measure_lmax
    )
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
        transfer=transfer,
        noise_shaping=shapings[0],
        noise_h_shaping=shapings[1] if kinds == 2 else np.zeros(0),
        matrix=matrix,
        moments=moments.values if carries_systematics else np.zeros(0),
        hits=hits,
        condition=condition,
        good=good,
        carries_systematics=carries_systematics,
        cmb_bb_excess=excess,
    )


def _eigen_factor(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvectors (n, d, d), sqrt of the eigenvalues clipped at 0 (n, d)) of (n, d, d)."""
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    return eigenvectors, np.sqrt(np.clip(eigenvalues, 0, None))


def _gaussian(factor: tuple[np.ndarray, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """(n, d) draws x = V sqrt(lambda) z, z ~ N(0, 1), with (V, sqrt(lambda)) = ``factor``."""
    eigenvectors, root_eigenvalues = factor
    z = rng.standard_normal(root_eigenvalues.shape)
    return np.einsum("pij,pj->pi", eigenvectors, root_eigenvalues * z)


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
