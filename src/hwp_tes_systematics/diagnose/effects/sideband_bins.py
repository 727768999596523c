"""The sidebands' bins: the modes of a periodogram grouped BIN_WIDTH wide in ln f and in
ln |f - f_0| (f_0 = 2 f_HWP, one side of it at a time), over which a white + 1/f noise and
a gain fluctuation's sidebands are constant to ~1e-2 of themselves, so that the Whittle
likelihoods of :mod:`.fluctuations` and :mod:`.coherence` need the bins' sums only."""

from __future__ import annotations

import numpy as np

BIN_WIDTH = 0.005  # the sideband bins' relative width in f and in |f - f_0|


def bin_labels(f, carrier_hz):
    """(bin in f, bin in |f - f_0|, the side of f_0) of each mode: the sidebands' bins,
    BIN_WIDTH wide in ln f and in ln |f - f_0|, over which S, E and C are constant to ~1e-2
    of themselves."""
    offset = f - carrier_hz
    in_f = np.floor(np.log(f) / BIN_WIDTH).astype(np.int64)
    in_offset = np.floor(np.log(np.abs(offset)) / BIN_WIDTH).astype(np.int64)
    return in_f, in_offset, (offset > 0).astype(np.int64)


def sum_in_bins(f, carrier_hz, powers, cross):
    """(mean f, modes, summed periodograms, summed cross-periodogram) per bin
    (:func:`bin_labels`)."""
    in_f, in_offset, side = bin_labels(f, carrier_hz)
    key = (
        (in_f - in_f.min()) * 4 * (np.abs(in_offset).max() + 2)
        + 2 * (in_offset - in_offset.min())
        + side
    )
    _, index = np.unique(key, return_inverse=True)
    counts = np.bincount(index).astype(float)
    mean_f = np.bincount(index, weights=f) / counts
    summed = [np.bincount(index, weights=p) for p in powers]
    if cross is not None:
        cross = np.bincount(index, weights=cross.real) + 1j * np.bincount(index, weights=cross.imag)
    return mean_f, counts, summed, cross
