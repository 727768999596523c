"""A filtered chunk binned into the map-makers of one pass: the binned solve's normal
equations (:func:`bin_chunk`), the HWP-demodulated streams (:func:`demodulated_streams`,
:func:`bin_streams`), and the extra map-makers that share the pass's TODs
(:class:`ExtraBinning`, :func:`bin_extra_binnings`). Called by :func:`.tod_maps.accumulate`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .baselines import baseline_samples, remove_baselines
from .demodulation import decimation_factor, demodulate
from .mapmaking import NormalEquations, PixelMoments
from .tod_filter import FilteredStack, baselines_removed

log = logging.getLogger(__name__)

# Bin the demodulated streams at every D-th sample (demodulation.decimation_factor)? The
# streams are the same band-limited signals, but the map's noise then follows the
# decimated hits: at nside 32, one day, D = 7, the seeds' E/B noise at ell 2-24 went from
# +17 % to +32 % of the full path's, and at nside 512 seven samples at 19 Hz are a pixel
# crossing. Off until validated at the resolutions it would serve (issue 27).
DECIMATE_DEMODULATED = False


@dataclass
class ExtraBinning:
    """Another map-maker fed by the same TODs in the same pass (the map-domain fixed pass's
    variants, :func:`fixed_maps.fixed_passes`): its HEALPix resolution (pixels from the
    pointing's directions; the sky is scanned at the primary resolution) and baseline
    length (None: none, and the HWP-harmonic fit without a constant, as the primary path
    would run it), with its own normal equations, HWPSS moments (one object may be shared
    by the binnings of one resolution) and calibration equations, filled by
    :func:`accumulate` as the primary ones."""

    nside: int
    baseline_length_s: float | None
    moments: PixelMoments | None = None
    equations: NormalEquations | None = None
    calibration_equations: NormalEquations | None = None
    # HWP demodulation + low-pass (:mod:`demodulation`) instead of the binned solve: then
    # ``equations`` and ``calibration_equations`` (the filtered calibration TODs) are
    # DemodulatedEquations, ``white_equations`` bins the unfiltered noise TODs (the white
    # reference of the noise shaping) and ``matrix_equations`` the binned solve's M of
    # every chunk (the white noise the seeds draw), both NormalEquations
    demodulated: bool = False
    white_equations: NormalEquations | None = None
    matrix_equations: NormalEquations | None = None


def bin_chunk(target, calibration_target, pixels, angles, binned, filtered, calibration, noise):
    """Bin a chunk's filtered TOD stack at ``pixels`` into ``target`` and, when
    ``calibration_target`` is given, the filtered ``calibration`` TODs then the unfiltered
    ``noise`` TODs (each (rows, n_det, n)) into it. ``binned``: (rows, owners), TOD i of
    ``target`` being row ``rows[i]`` of ``filtered`` (detector ``owners[i]`` only unless
    None); ``angles``: (cos 2 alpha, sin 2 alpha, weights, pol_efficiency)."""
    rows, owners = binned
    target.add(pixels, *angles, filtered, owners, rows=rows)
    if calibration_target is not None:
        calibration_target.add(pixels, *angles, [*calibration, *noise])


def demodulated_streams(stack, pointing, inner, rates, threads, clock) -> tuple:
    """(streams, picked): the demodulated streams (L d, L(2 d cos 4 chi), L(2 d sin 4
    chi)) of a filtered TOD stack (rows, n_det, n, with margins: the low-pass wraps
    around) at the ``inner`` samples, or at every D-th of them with DECIMATE_DEMODULATED
    (:func:`demodulation.decimation_factor`), (3, rows, n_det, n_kept), and ``picked``,
    the slice of the inner samples they are at; ``rates``: (sampling rate, f_HWP) [Hz]."""
    sampling_rate_hz, f_hwp_hz = rates
    stride = decimation_factor(sampling_rate_hz, f_hwp_hz) if DECIMATE_DEMODULATED else 1
    with clock("demodulation"):
        streams = demodulate(
            stack, pointing.hwp_angle_rad, sampling_rate_hz, f_hwp_hz, threads, stride
        )
    first, stop = -(-inner.start // stride), -(-inner.stop // stride)  # ceilings
    return streams[..., first:stop], slice(first * stride - inner.start, None, stride)


def _shared_streams(cache: dict, kind: str, filtered: FilteredStack, offset: bool, demodulation):
    """:func:`demodulated_streams` of ``filtered[offset]`` (``demodulation``: its other
    arguments), computed once per chunk and kind of stack (``cache``). The demodulation
    is linear: when both fits come from one filtering, the streams with the constant are
    those without it less c times those of u_f (:class:`FilteredStack`), so the stack is
    demodulated once, not once per fit (equal to rounding)."""
    key = (kind, offset)
    if key in cache:
        return cache[key]
    if offset and filtered.coefficients is not None:
        streams, picked = _shared_streams(cache, kind, filtered, False, demodulation)
        u_streams, _ = demodulated_streams(filtered.filtered_u, *demodulation)
        coefficients = filtered.coefficients.astype(streams.dtype)[None, ..., None]
        cache[key] = (streams - coefficients * u_streams[:, None], picked)
    else:
        cache[key] = demodulated_streams(filtered[offset], *demodulation)
    return cache[key]


def bin_streams(target, demodulated, binned, pixels, pointing, inner, detector, samples, clock):
    """Bin demodulated streams (:func:`demodulated_streams`: (streams, picked)) into
    ``target`` (DemodulatedEquations) at their samples, baselines of ``samples`` (None:
    none; in full-rate samples) removed from a copy of the intensity stream only (the
    streams may serve other map-makers). ``pixels``: of the inner samples;
    ``binned``: (rows, owners), TOD i of ``target`` being row ``rows[i]`` (detector
    ``owners[i]`` only unless None); ``detector``: (weights, pol_efficiency)."""
    streams, picked = demodulated
    rows, owners = binned
    weights, pol_efficiency = detector
    if samples is not None:
        per_baseline = max(1, round(samples / picked.step))
        intensity = remove_baselines(streams[0][list(rows)], per_baseline)
        tods = [
            np.stack([intensity[i], streams[1, row], streams[2, row]]) for i, row in enumerate(rows)
        ]
    else:
        tods = [streams[:, row] for row in rows]
    with clock("binning"):
        target.add(
            pixels[:, picked],
            pointing.cos_2alpha[:, inner][:, picked],
            pointing.sin_2alpha[:, inner][:, picked],
            pointing.hwp_angle_rad[inner][picked],
            weights,
            pol_efficiency,
            tods,
            owners,
        )


def _bin_demodulated(
    extra, calibrating, pixels, pointing, inner, detector, binned, streams, rate_hz, clock
) -> None:
    """Bin a chunk into a demodulated extra binning (:func:`bin_streams`): the filtered
    TODs' demodulated streams, on calibration chunks the filtered calibration TODs' too
    and, unless a binned map-maker of its nside holds them (``matrix_equations`` None
    until the end), the unfiltered noise TODs binned as they are and M of every chunk.
    ``detector``: (weights, pol_efficiency); ``binned``: (rows, owners); ``streams``: (the
    filtered TODs' streams, the calibration TODs' streams, the unfiltered noise TODs)."""
    filtered, calibration_filtered, unfiltered_noise = streams
    samples = baseline_samples(extra.baseline_length_s, rate_hz)
    todo = [(extra.equations, filtered, binned)]
    if calibrating:
        n_filtered = extra.calibration_equations.n_tods
        todo.append((extra.calibration_equations, calibration_filtered, (range(n_filtered), None)))
    for target, target_streams, target_rows in todo:
        bin_streams(
            target, target_streams, target_rows, pixels, pointing, inner, detector, samples, clock
        )
    if extra.matrix_equations is None:  # shared with the binned map-maker of its nside
        return
    angles = (pointing.cos_2alpha[:, inner], pointing.sin_2alpha[:, inner], *detector)
    with clock("binning"):
        extra.matrix_equations.add(pixels, *angles, np.empty((0, *pixels.shape)), rows=[])
        if calibrating:
            extra.white_equations.add(pixels, *angles, unfiltered_noise)


def bin_extra_binnings(extra_binnings, chunk, filtered, demodulation) -> None:
    """Bin a chunk into each extra binning (:class:`ExtraBinning`), with or without its
    baselines; a demodulated one through :func:`_bin_demodulated`, the streams demodulated
    once per stack and baseline choice whatever the map-makers' nsides.
    ``chunk``: (calibrating, {nside: pixels}, angles, (rows, owners), the unfiltered noise
    TODs); ``filtered``: ({offset: filtered stack}, {offset: filtered calibration stack});
    ``demodulation``: (pointing, inner, (sampling rate, HWP frequency), threads, clock)."""
    calibrating, pixels_of, angles, binned, unfiltered_noise = chunk
    notched_of, calibration_of = filtered
    pointing, inner, (rate_hz, _), _, clock = demodulation
    streams_of = {}
    for extra in extra_binnings:
        offset = extra.baseline_length_s is not None
        if extra.demodulated:
            _bin_demodulated(
                extra,
                calibrating,
                pixels_of[extra.nside],
                pointing,
                inner,
                angles[2:],
                binned,
                (
                    _shared_streams(streams_of, "filtered", notched_of, offset, demodulation),
                    _shared_streams(streams_of, "calibration", calibration_of, offset, demodulation)
                    if calibrating
                    else None,
                    unfiltered_noise,
                ),
                rate_hz,
                clock,
            )
            continue
        stacks = baselines_removed(
            [notched_of[offset], calibration_of[offset]], inner, extra.baseline_length_s, rate_hz
        )
        with clock("binning"):
            bin_chunk(
                extra.equations,
                extra.calibration_equations if calibrating else None,
                pixels_of[extra.nside],
                angles,
                binned,
                *stacks,
                unfiltered_noise,
            )
        del stacks


def share_binned_matrices(extra_binnings, binned_of: dict, calibration) -> None:
    """A demodulated map-maker without its own matrix takes the binned one of its
    resolution, and the unfiltered noise TODs (the binned calibration's last ones)."""
    for extra in extra_binnings:
        if extra.demodulated and extra.matrix_equations is None:
            binned, binned_calibration = binned_of[extra.nside]
            extra.matrix_equations = binned.subset([])
            if binned_calibration is not None:  # its last TODs: the noise unfiltered
                n_tods = binned_calibration.n_tods
                unfiltered = range(n_tods - calibration.n_noise_tods, n_tods)
                extra.white_equations = binned_calibration.subset(unfiltered)
