"""The filter as functions of multipole: what the fixed pass measures of the TOD filter
(HWP-harmonic removal, notch, offsets) on its binned maps, and how the seeds apply it.

T_ell = C_ell(bin F CMB, CMB) / C_ell(CMB) (TT, EE; BB from the reference's B modes alone,
:func:`measure_cmb_response`) is the transfer of a reference CMB through the filter; the
noise shaping S_ell ~ sqrt(sum C_ell(bin F n) / sum C_ell(bin n)) is that of reference
noise realizations, binned SHAPING_BIN_WIDTH multipoles at a time and corrected
SHAPING_ITERATIONS times for the mask's mode coupling. A seed's filtered map is
its a_lm times T_ell (:func:`transferred_map`) and its noise white noise times S_ell
(:func:`shaped_noise_map`): the approximation of the map-domain path
(:mod:`map_domain`), validated against the TOD path there.

T_ell is a cross spectrum: a filter that scales each mode by t gives T = t and t^2 of the
power, one that keeps or removes modes whole gives T and T of the power, and one that
mixes modes (the notch and the offsets along a scan, E into B) gives more power than
T^2. What the filtered map holds of BB beyond the emulation T a_lm is measured as two
excess ratios E_ell (:func:`measure_excess_bb`), over the reference's BB, by origin: its
B modes (the B-to-B auto transfer is T^2 + E_B) and its T and E modes (the filter's own
leakage into B, beyond the mask's, which the emulation keeps); the seeds add Gaussian B
fields of those powers (:func:`excess_bb_alms`).
"""

from __future__ import annotations

import healpy as hp
import numpy as np

from ..sky import harmonics

SHAPING_BIN_WIDTH = 4  # multipoles averaged in the noise shaping
SHAPING_ITERATIONS = 2  # corrections of the noise shaping for the mask's mode coupling
TRANSFER_SPECTRA = ("tt", "ee", "bb")
EXCESS_ORIGINS = ("b_modes", "te_modes")  # rows of the BB excess (measure_excess_bb)


def b_modes_alone(alm: np.ndarray) -> np.ndarray:
    """T, E, B a_lm (3, nalm) with T and E set to zero: the B modes of ``alm`` alone."""
    b_alm = np.zeros_like(alm)
    b_alm[2] = alm[2]
    return b_alm


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


def measure_cmb_response(
    outputs_iqu: tuple[np.ndarray, np.ndarray],
    input_iqu: np.ndarray,
    input_alm: np.ndarray,
    good: np.ndarray,
    lmax: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(T_ell (3, lmax + 1), E_ell (2, lmax + 1)) of the filter on a reference CMB, from
    ``outputs_iqu`` = (F CMB, F CMB_B), the filtered-binned reference and its B modes
    alone: T_ell of TT and EE from the whole reference, of BB from its B modes alone (in
    one realization, the T and E modes the filter leaks into B correlate with its B
    modes by chance, which a whole-reference T_BB reads as transfer: on M1-140's sampled
    year T_BB^2 came out 0.17 at ell 2-10 where its B modes alone give T_BB = 0.004), and the
    BB excess of :func:`measure_excess_bb` against that T_ell. ``input_iqu``: the
    reference's map, ``input_alm`` its a_lm (band >= ``lmax``)."""
    full_output, b_output = outputs_iqu
    transfer = measure_transfer(full_output, input_iqu, good, lmax)
    b_alm = b_modes_alone(input_alm)
    b_input = harmonics.alm2map(b_alm, hp.npix2nside(good.size), hp.Alm.getlmax(b_alm.shape[-1]))
    transfer[2] = measure_transfer(b_output, b_input, good, lmax)[2]
    return transfer, measure_excess_bb(outputs_iqu, input_alm, transfer, good, lmax)


def measure_excess_bb(
    outputs_iqu: tuple[np.ndarray, np.ndarray],
    input_alm: np.ndarray,
    transfer: np.ndarray,
    good: np.ndarray,
    lmax: int,
) -> np.ndarray:
    """(2, lmax + 1) the BB the filtered reference holds beyond its emulation, over the
    reference's BB, by origin (EXCESS_ORIGINS): with ``outputs_iqu`` = (F CMB, F CMB_B)
    the filtered-binned maps of the reference and of its B modes alone, and Em(x) =
    :func:`filtered_cmb_map` of x with ``transfer``,

        E_B  = [C_BB(F CMB_B) - C_BB(Em(CMB_B))] / C_BB(CMB_B)
        E_TE = [C_BB(F CMB - F CMB_B) - C_BB(Em(CMB - CMB_B))] / C_BB(CMB_B)

    pseudo-spectra on ``good`` (so the mask's own mixing, which the emulation keeps,
    cancels), summed over SHAPING_BIN_WIDTH multipoles before the ratio (one
    realization's scatter); 0 below ell = 2. ``input_alm``: the reference's a_lm (3,
    nalm) at its band (the map-maker's, >= ``lmax``)."""
    nside = hp.npix2nside(good.size)
    band = hp.Alm.getlmax(input_alm.shape[-1])
    b_alm = b_modes_alone(input_alm)
    full_output, b_output = outputs_iqu
    origins = [(b_output, b_alm), (full_output - b_output, input_alm - b_alm)]
    unfiltered = [harmonics.alm2map(alm, nside, band) for _, alm in origins]
    total = _binned_pseudo_spectra(unfiltered[0], good, lmax)[2]  # the reference's B modes
    excess = np.zeros((len(EXCESS_ORIGINS), lmax + 1))
    for row, ((output, alm), unfiltered_map) in enumerate(zip(origins, unfiltered, strict=True)):
        emulated = filtered_cmb_map(unfiltered_map, alm, transfer, band, lmax)
        difference = (
            _binned_pseudo_spectra(output, good, lmax)[2]
            - _binned_pseudo_spectra(emulated, good, lmax)[2]
        )
        np.divide(difference, total, out=excess[row], where=total > 0)
    excess[:, :2] = 0.0
    return excess


def excess_bb_alms(
    excess: np.ndarray, unit_alms: np.ndarray, reference_bb_k2: np.ndarray, lmax: int
) -> np.ndarray:
    """(n, 3, nalm) the B-mode a_lm [K_CMB] a seed adds to its emulated filtered CMB, by
    origin (EXCESS_ORIGINS; n = 2, or the first n of them), up to ``lmax``:

        a_B = sqrt(max(E_ell, 0) C_ell^BB) u_lm,

    with ``excess`` E_ell of :func:`measure_excess_bb`, ``reference_bb_k2`` the BB
    [K_CMB^2] at the channel's beam that E_ell multiplies (one spectrum for every origin,
    or one row per origin) and ``unit_alms`` (n, nalm) B fields of unit power
    (:func:`sky.cmb.filter_excess_unit_alms`, the same for every channel: the filters'
    mixing is taken as common to the channels, which the HILC then cannot average down)."""
    unit_alms = np.atleast_2d(unit_alms)
    n_rows = unit_alms.shape[0]
    reference = np.atleast_2d(reference_bb_k2)[:, : lmax + 1]
    reference = np.broadcast_to(reference, (n_rows, reference.shape[1]))
    out = np.zeros((n_rows, 3, unit_alms.shape[-1]), dtype=complex)
    for row in range(n_rows):
        power = np.clip(excess[row, : lmax + 1], 0.0, None) * reference[row]
        out[row, 2] = hp.almxfl(unit_alms[row], np.sqrt(power))
    return out
