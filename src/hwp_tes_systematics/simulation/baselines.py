"""Per-detector baseline (offset) removal before map-making.

Each detector's TOD carries an offset of its own: the readout's, and the DC term that
the nonlinearity adds, g1 <d^2> ~ g1 A_2^2 / 2, which differs between the two
detectors of a pair when each has its own g1. A binned map-maker turns a difference of
offsets between the detectors into Q and U wherever the HWP angles of a pixel's
samples do not average cos 4 chi and sin 4 chi to zero (short observations: a unit
offset in one detector leaks 7-9 % into one-day Q/U maps). Real pipelines remove
baselines first (a destriper fits them jointly with the map).

Here the baseline of detector k on interval j is the mean of its TOD over the
interval, and it is subtracted:

    d_k(t) -> d_k(t) - (1 / n_j) sum_{t' in j} d_k(t'),       t in interval j,

intervals of ``baseline_samples`` consecutive samples from the start of each chunk
(the last one of a chunk may be shorter). The operator is linear (the decomposition
m(g1) = m_nosys + sum_k g1_k T_k still holds) and removes any constant per interval
exactly; sky polarisation, modulated at 4 f_HWP, has a mean over an interval of
~1e-4 of its amplitude and passes. The sky's intensity loses its mean per interval,
as in any pipeline that removes offsets; the references of the residuals pass through
the same operator.

Why not litebird_sim's destriper (``lbs.make_destriped_map``): it solves baselines and
map jointly by conjugate gradients over the whole mission held in memory (TOD and
pointings of all samples: ~60 GB for one year of one pair), while this pipeline
accumulates the normal equations chunk by chunk in bounded memory, and would have to
run once per TOD of the linear decomposition. With a HWP the Q/U signal sits at
4 f_HWP and does not need the destriper's joint solution; what the offsets need is
their removal, which the interval mean does exactly.
"""

from __future__ import annotations

import numpy as np


def baseline_samples(baseline_length_s: float | None, sampling_rate_hz: float) -> int | None:
    """Samples per baseline interval (at least 1), or None when no baselines are removed."""
    if baseline_length_s is None:
        return None
    return max(1, round(baseline_length_s * sampling_rate_hz))


def remove_baselines(tod: np.ndarray, samples_per_baseline: int | None) -> np.ndarray:
    """Subtract, in place, the mean of every interval of ``samples_per_baseline`` samples
    from each row of ``tod`` (any leading shape, time last); returns ``tod``.
    None leaves the TOD as it is (the paper-literal path)."""
    if samples_per_baseline is None:
        return tod
    for start in range(0, tod.shape[-1], samples_per_baseline):
        interval = tod[..., start : start + samples_per_baseline]
        interval -= interval.mean(axis=-1, keepdims=True)
    return tod
