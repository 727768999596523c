"""The filter of a chunk's TOD (any leading shape, time last): the HWP-harmonic template
removal (with or without a constant), the paper's 4 f_HWP notch on the chunk with its
margins, then the per-detector baselines on its inner samples. Linear in the TOD, so the
map of d + g1 d^2 is the map of d plus g1 times the map of d^2 (:mod:`.tod_maps`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .baselines import baseline_samples, remove_baselines
from .hwpss_removal import offset_residual, remove_hwp_harmonics
from .notch import apply_notch, notch_width_hz

log = logging.getLogger(__name__)


@dataclass
class FilteredStack:
    """A chunk's TOD stack (rows, n_det, n) filtered with each HWP-harmonic fit in use:
    ``stack[offset]`` (with a constant in the fit if True). When both fits come from one
    filtering (:func:`filter_both_offsets`), ``coefficients`` c (rows, n_det) and
    ``filtered_u`` u_f (n_det, n) relate them: with = without - c u_f, so that any
    linear operation on the stacks (the demodulation) needs the one without and u_f only."""

    of: dict[bool, np.ndarray]
    coefficients: np.ndarray | None = None
    filtered_u: np.ndarray | None = None

    def __getitem__(self, offset: bool) -> np.ndarray:
        return self.of[offset]


def filter_both_offsets(unfiltered, pointing, simulator, settings) -> FilteredStack:
    """The HWP-harmonic removal (with and without a constant) then notch of a chunk's TOD
    stack (rows, n_det, n), both from one filtering: the fit without a constant, then
    the constant projected out through the same filter (:func:`hwpss_removal.offset_residual`;
    equal to filtering twice, to round-off). ``unfiltered`` is overwritten."""
    harmonics = settings.removed_hwp_harmonics
    u = offset_residual(
        pointing.hwp_angle_rad, harmonics, pointing.harmonic_templates(harmonics, offset=False)
    )
    coefficients = (unfiltered @ u) / (u @ u)  # (rows, n_det): c = <u, d> / <u, u>
    u_rows = np.broadcast_to(u.astype(unfiltered.dtype), (1, *unfiltered.shape[1:]))
    stack = np.concatenate([unfiltered, u_rows])
    notched = notch_with_margins(stack, pointing, simulator, settings, overwrite=True, offset=False)
    without, filtered_u = notched[:-1], notched[-1]
    with_offset = without - coefficients[..., None] * filtered_u
    return FilteredStack({False: without, True: with_offset}, coefficients, filtered_u)


def filter_offsets(unfiltered, offsets, pointing, simulator, settings) -> FilteredStack:
    """The chunk's TOD stack (rows, n_det, n) filtered for each HWP-harmonic fit in
    ``offsets`` (with a constant if True): one filtering for both
    (:func:`filter_both_offsets`). ``unfiltered`` is overwritten; its dtype is kept."""
    if len(offsets) == 1:
        (offset,) = offsets
        return FilteredStack(
            {
                offset: notch_with_margins(
                    unfiltered, pointing, simulator, settings, overwrite=True, offset=offset
                )
            }
        )
    return filter_both_offsets(unfiltered, pointing, simulator, settings)


def filter_tod(
    tod: np.ndarray, pointing, inner: slice, simulator, settings, overwrite: bool = False
) -> np.ndarray:
    """HWP-harmonic template removal, then the paper's 4 f_HWP notch, on a chunk with
    margins (any leading shape, time last); returns the ``inner`` samples, from which the
    per-detector baselines are removed (:mod:`baselines`; none on the paper-literal path,
    where the harmonic fit has no constant either).
    Linear in the TOD. ``overwrite`` lets the HWP-harmonic removal reuse ``tod``'s memory."""
    notched = notch_with_margins(tod, pointing, simulator, settings, overwrite)
    return remove_baselines(notched[..., inner], baseline_samples_of(settings))


def notch_with_margins(tod, pointing, simulator, settings, overwrite: bool = False, offset=None):
    """HWP-harmonic template removal (with a constant when baselines are removed, or as
    ``offset`` says), then the notch (none when ``settings.notch_width_divisor`` is
    None), on the whole chunk with its margins."""
    f_hwp_hz = simulator.channel.hwp_frequency_hz
    offset = settings.baseline_length_s is not None if offset is None else offset
    harmonics = settings.removed_hwp_harmonics
    cleaned = remove_hwp_harmonics(
        tod,
        pointing.hwp_angle_rad,
        harmonics,
        overwrite=overwrite,
        offset=offset,
        templates=pointing.harmonic_templates(harmonics, offset),
    )
    if settings.notch_width_divisor is None:
        return cleaned
    return apply_notch(
        cleaned,
        settings.plan.sampling_rate_hz,
        f_hwp_hz,
        notch_width_hz(f_hwp_hz, settings.notch_width_divisor),
        workers=settings.threads,
    )


def baseline_samples_of(settings) -> int | None:
    """Samples per baseline interval of the settings (None: no baselines)."""
    return baseline_samples(settings.baseline_length_s, settings.plan.sampling_rate_hz)


def baselines_removed(stacks, inner, baseline_length_s, sampling_rate_hz) -> list:
    """The stacks' inner samples, with the baselines of ``baseline_length_s`` removed
    (on copies: the removal works in place) when it is not None; None stays None."""
    stacks = [None if stack is None else stack[..., inner] for stack in stacks]
    if baseline_length_s is None:
        return stacks
    samples = baseline_samples(baseline_length_s, sampling_rate_hz)
    return [None if stack is None else remove_baselines(stack.copy(), samples) for stack in stacks]
