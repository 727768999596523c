"""Where a readout step may be, and whether it is sharp: the scan of a residual over a
step's time by cumulative sums, and the test of a candidate against a linear ramp
(:mod:`.steps` for the model and the effect; :mod:`.step_search` for the exact fit).

A step at t_s (its first sample after it) in detector k: d -> d + H(t - t_s) [o + s d],
o the offset jump [K], s the relative gain jump. For every candidate t_s the Whittle fit
of the two templates T_o = H v and T_g = H c v (v the valid samples, c the part of d_nom
above f_HWP / 2, the carrier) to the residual R, each alone:

    delta chi^2(t_s) = <T_o, R>^2 / <T_o, T_o> + <T_g, R>^2 / <T_g, T_g>

with <a, b> = sum_f 2 Re(a_f* b_f) w_f (:mod:`..linalg`). <T, R> = n sum_t T(t) (W R)(t)
(W R = irfft(w R_f)), a cumulative sum over t >= t_s; <T_o, T_o> = n [L k_0 + 2 sum_{l<L}
(L - l) k_l] (k = irfft(w), L = n - t_s) where every sample is valid; <T_g, T_g> ~ n w_c P (1 - P /
P_0), P = sum_{t>=t_s} c(t)^2 (w_c the weight at 2 f_HWP, where c lives; the factor: the
step's mean taken by the nominal 2f amplitude).

A linear ramp over a width W is the mean of the steps over W, so its projections are
running means of the scan's and its norms the step's plus a part local to W
(:func:`sharpness`).

The offset's templates are fitted beside the recording's linear trend R (:func:`trend`):
T_o' = T_o - a^T G^-1 N, N the nuisance templates (R, and v where samples are flagged),
a = <T_o, N>, G = <N, N>. The Whittle likelihood takes the residual as periodic,
so a step at t_s is also a jump back at the recording's end; 1/f noise does not come back
to where it started (its end and start differ as two points far apart do), and without R
every step's fit would take that difference as information: on TOAST's 1/f noise an
offset step's z at a random time had a spread of 1.7-2, not 1, and its error was up to
sqrt(2) too small (``benchmarks/step_calibration.py``). With flagged samples the offset's
templates are also fitted beside the gap offset v (the nominal model's constant on the
valid samples, :mod:`..select.bank`): the zero-filled gap is a box as deep as the noise's
level there, which a step before the gap (H v holds the box) would otherwise take, its z
spreading over 2 sigma and more; and <T_o, T_o> holds the mask
(:func:`masked_offset_norms`) as the projections do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fourier import irfft, rfft

# a step is compared with the linear changes over RAMP_S centred within RAMP_S of it: a
# readout step is one sample sharp, a drift or a modulation smooth over minutes
RAMP_S = 180.0
RAMP_CENTRES = 9  # the ramp's centres tried, evenly over +- RAMP_S
# the parts a step may have: an offset jump, a gain jump or both (each step takes the one
# of the three its BIC prefers; its count: the parts and its time)
PARTS = ("offset", "gain")


def carrier(signal: np.ndarray, f_cut_hz: float, sampling_rate_hz: float) -> np.ndarray:
    """The part of a detector's signal above ``f_cut_hz`` (the HWPSS and its lines)."""
    n = signal.size
    spectrum = rfft(signal)
    spectrum[np.fft.rfftfreq(n, 1.0 / sampling_rate_hz) < f_cut_hz] = 0.0
    return irfft(spectrum, n=n)


def _box_norms(kernel: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """sum_{i, j < L} k_(i - j) for boxes of length L: L k_0 + 2 sum_{l < L} (L - l) k_l."""
    lags = np.arange(1, kernel.size)
    first = np.concatenate([[0.0], np.cumsum(kernel[1:])])  # sum_{l=1}^{m} k_l, m = 0..n-1
    moment = np.concatenate([[0.0], np.cumsum(lags * kernel[1:])])
    m = np.clip(lengths - 1, 0, kernel.size - 1)
    return lengths * kernel[0] + 2.0 * (lengths * first[m] - moment[m])


@dataclass(frozen=True)
class ScanNorms:
    """What a scan needs that depends on the weights, the mask and the carrier only, not
    on the residual (:meth:`of`): computed once per detector and noise model."""

    valid: np.ndarray
    carrier_k: np.ndarray
    w_carrier: float
    offset_norm: np.ndarray  # <T_o', T_o'>
    gain_norm: np.ndarray  # <T_g', T_g'>
    carrier_power: np.ndarray  # c^2 v per sample
    power_after: np.ndarray  # P(t_s) = sum_{t >= t_s} c^2 v
    fraction: np.ndarray  # P / P_0
    inverse_norms: dict  # part -> 1 / <T, T>, 0 where the norm vanishes
    trend_f: np.ndarray  # the rfft of R v, the linear trend on the valid samples
    nuisance: np.ndarray  # N (m, n): R v, and v where samples are flagged
    nuisance_after: np.ndarray  # a = <T_o, N> (m, n) at every t_s
    nuisance_inverse: np.ndarray  # G^-1 (m, m)

    @classmethod
    def of(cls, w, valid, carrier_k, w_carrier: float, offset_norm=None) -> ScanNorms:
        """``offset_norm``: <T_o, T_o> at every t_s with the mask ``valid``
        (:func:`offset_norms` where every sample is valid, else
        :func:`masked_offset_norms`) if known."""
        n = valid.size
        if offset_norm is None:
            offset_norm = offset_norms(w, n) if valid.all() else masked_offset_norms(w, valid)
        trend_v = trend(n) * valid
        trend_f = rfft(trend_v)
        nuisance = np.stack([trend_v] if valid.all() else [trend_v, valid * 1.0])
        weighted = irfft(w * rfft(nuisance, axis=-1), n=n, axis=-1)  # K N
        # a = <T_o, N> = n sum_{t >= t_s} v (K N), G = <N, N>
        nuisance_after = n * np.cumsum((weighted * valid)[:, ::-1], axis=-1)[:, ::-1]
        inverse = np.linalg.pinv(n * (nuisance @ weighted.T), hermitian=True)
        offset_norm = offset_norm - np.einsum(
            "it,ij,jt->t", nuisance_after, inverse, nuisance_after
        )
        carrier_power = carrier_k**2 * valid
        power_after = np.cumsum(carrier_power[::-1])[::-1]
        fraction = power_after / max(power_after[0], 1e-300)
        # both parts projected off the carrier itself (the nominal 2f amplitude takes the
        # step's mean): T_g - (P / P_0) c
        gain_norm = n * w_carrier * power_after * (1.0 - fraction)
        return cls(
            valid=valid,
            carrier_k=carrier_k,
            w_carrier=w_carrier,
            offset_norm=offset_norm,
            gain_norm=gain_norm,
            carrier_power=carrier_power,
            power_after=power_after,
            fraction=fraction,
            inverse_norms={"offset": _inverse(offset_norm), "gain": _inverse(gain_norm)},
            trend_f=trend_f,
            nuisance=nuisance,
            nuisance_after=nuisance_after,
            nuisance_inverse=inverse,
        )


def trend(n: int) -> np.ndarray:
    """The linear trend over ``n`` samples, t / n - 1/2: what the offset steps are fitted
    beside (module docstring)."""
    return np.arange(n) / n - 0.5


def _inverse(norm: np.ndarray) -> np.ndarray:
    """1 / norm where it is above 1e-12 of its largest, else 0."""
    good = norm > 1e-12 * max(norm.max(), 1e-300)
    out = np.zeros(norm.size)
    out[good] = 1.0 / norm[good]
    return out


@dataclass(frozen=True)
class StepScan:
    """Each part's projection <T, R> for a step at every sample t_s (module docstring),
    with the norms (:class:`ScanNorms`) its delta chi^2 and a ramp's are built from."""

    offset: np.ndarray  # <T_o, R>
    gain: np.ndarray  # <T_g', R>, T_g' = T_g projected off the carrier
    norms: ScanNorms

    def projection(self, part: str) -> np.ndarray:
        return self.offset if part == "offset" else self.gain

    def value(self, part: str, index: int) -> float:
        """The part's value fitted alone at ``index``: <T, R> / <T, T>."""
        return float(self.projection(part)[index] * self.norms.inverse_norms[part][index])

    def chi2(self, part: str) -> np.ndarray:
        """delta chi^2 = <T, R>^2 / <T, T> of ``part`` alone at every sample."""
        projection = self.projection(part)
        return projection * projection * self.norms.inverse_norms[part]

    def chi2_at(self, part: str, index: int) -> float:
        """delta chi^2 of ``part`` alone at ``index``."""
        return float(self.projection(part)[index] ** 2 * self.norms.inverse_norms[part][index])


def offset_norms(w: np.ndarray, n: int) -> np.ndarray:
    """<H(t - t_s), H(t - t_s)> at every t_s, every sample valid (:func:`_box_norms`)."""
    return n * _box_norms(irfft(w, n=n), n - np.arange(n))


def masked_offset_norms(w: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """<H(t - t_s) v, H(t - t_s) v> at every t_s, v the valid samples:
    n sum_{i >= t_s} v_i (k_0 v_i + 2 c_i), c_i = sum_{l >= 1} k_l v_{i + l} (v zero after
    the end; the box's lags are below n, where the circular kernel k = irfft(w) is
    k_{|i - j|}). c is a correlation, one transform pair over 2n samples (no wrap)."""
    n = valid.size
    kernel = irfft(w, n=n)
    v = valid.astype(float)
    size = 2 * n
    lagged = np.zeros(size)
    lagged[1:n] = kernel[1:]
    padded = np.zeros(size)
    padded[:n] = v
    c = irfft(rfft(padded) * np.conj(rfft(lagged)), n=size)[:n]
    return n * np.cumsum((v * (kernel[0] * v + 2.0 * c))[::-1])[::-1]


def scan_parts(
    r_f: np.ndarray,
    w: np.ndarray,
    valid: np.ndarray,
    carrier_k: np.ndarray,
    w_carrier: float,
    offset_norm: np.ndarray | None = None,
) -> StepScan:
    """The :class:`StepScan` of residual ``r_f`` (:func:`scan_weighted`)."""
    norms = ScanNorms.of(w, valid, carrier_k, w_carrier, offset_norm)
    return scan_weighted(irfft(w * r_f, n=valid.size), norms)


def scan_weighted(weighted: np.ndarray, norms: ScanNorms) -> StepScan:
    """The :class:`StepScan` of the weighted residual W R = irfft(w R_f): cumulative sums
    over t >= t_s of W R v and of c W R v (module docstring)."""
    n = weighted.size
    masked = weighted * norms.valid
    after = np.cumsum(masked[::-1])[::-1]  # sum_{t >= t_s}
    gain_after = np.cumsum((norms.carrier_k * masked)[::-1])[::-1]
    gain_after -= norms.fraction * gain_after[0]
    after *= n
    # projected off the nuisance templates: <T_o', R_res> = <T_o, R_res> - a^T G^-1 <N, R_res>
    after -= (norms.nuisance_inverse @ (n * (norms.nuisance @ weighted))) @ norms.nuisance_after
    gain_after *= n
    return StepScan(offset=after, gain=gain_after, norms=norms)


def step_scan(
    r_f: np.ndarray, w: np.ndarray, valid: np.ndarray, carrier_k: np.ndarray, w_carrier: float
) -> dict[str, np.ndarray]:
    """{"offset", "gain"}: delta chi^2 of each part of a step at every sample (module
    docstring: each template alone)."""
    scan = scan_parts(r_f, w, valid, carrier_k, w_carrier)
    return {part: scan.chi2(part) for part in PARTS}


def ramp_offset_terms(w: np.ndarray, n: int, index: int, half: int) -> tuple[float, float]:
    """(C, E_1) of the offset's ramp of width 2 ``half`` centred at ``index`` (the mask
    ignored): the ramp is H(t - index - half) plus a part local to its width, so its norm
    is the step's there plus C, the same at centres nearby (away from the ends); E_1 =
    <H - ramp, H - ramp>, the step's information above 1 / width per unit offset. Both
    are computed once per detector, at the recording's middle."""
    step = edge_shape(n, index)
    ramp = edge_shape(n, index, 2 * half)
    later = edge_shape(n, min(index + half, n - 1))

    def norm(x: np.ndarray) -> float:
        return n * float(x @ irfft(w * rfft(x), n=n))

    return norm(ramp) - norm(later), norm(step - ramp)


def sharpness(scan: StepScan, index: int, half: int, parts, span, offset_terms) -> tuple:
    """(D, E) of the step of ``parts`` at sample ``index``: D its scan delta chi^2 less the best of linear changes over 2 ``half``
    samples centred at RAMP_CENTRES points within 2 ``half`` of it (each within ``span``,
    the samples (first, last) a step is sought in), E = ||values (T_step -
    T_ramp)||^2 at its own centre (the step's information above 1 / width, the values
    each part's scan estimate; ``offset_terms``: :func:`ramp_offset_terms`). A step gives
    D ~ +E +- 2 sqrt(E), a smooth change D ~ -E +- 2 sqrt(E).

    A ramp is the mean of the steps over its width, so its projection is the mean of
    theirs (a running mean of the scan's); its norm is the step's after it plus a part
    local to its width (:func:`ramp_offset_terms` for the offset; the gain's summed over
    the carrier's power, white at 2 f_HWP as in the scan). The linear templates fitted
    beside the step are left out: smooth over the recording, or lines, they hardly reach
    above 1 / width, where the two shapes differ."""
    n = scan.offset.size
    norms = scan.norms
    width = 2 * half
    p0 = max(norms.power_after[0], 1e-300)
    centres = np.linspace(index - width, index + width, RAMP_CENTRES).astype(int)
    # each ramp's last sample before it, the ramp inside the span
    lo_all = np.clip(centres - half, span[0], max(span[0], span[1] - width))
    rise = np.arange(1, width) / width  # the ramp inside its width
    ramps = np.zeros(lo_all.size)
    # the running means need the window the ramps span only
    first, last = int(lo_all.min()) + 1, int(lo_all.max()) + width + 1
    lo_local = lo_all + 1 - first
    for part in parts:
        running = np.concatenate([[0.0], np.cumsum(scan.projection(part)[first:last])])
        ramp_projection = (running[lo_local + width] - running[lo_local]) / width
        if part == "offset":
            ramp_norm = norms.offset_norm[lo_all + width] + offset_terms[0]
        else:
            power = np.concatenate([[0.0], np.cumsum(norms.power_after[first:last])])
            mean_power = (power[lo_local + width] - power[lo_local]) / width
            inside = np.array([rise**2 @ norms.carrier_power[lo + 1 : lo + width] for lo in lo_all])
            squared = norms.power_after[lo_all + width] + inside
            ramp_norm = n * norms.w_carrier * (squared - mean_power**2 / p0)
        good = ramp_norm > 0
        ramps[good] += ramp_projection[good] ** 2 / ramp_norm[good]
    step = sum(scan.chi2_at(part, index) for part in parts)
    information = 0.0
    for part in parts:
        value = scan.value(part, index)
        if part == "offset":
            information += value**2 * offset_terms[1]
            continue
        lo = min(max(index - half, 0), n - 1 - width)
        difference = np.where(np.arange(lo + 1, lo + width) >= index, 1.0, 0.0) - rise
        local = norms.carrier_power[lo + 1 : lo + width]
        spread = difference**2 @ local - (difference @ local) ** 2 / p0
        information += value**2 * n * norms.w_carrier * spread
    return step - float(ramps.max()), information


def edge_shape(n: int, index: int, width_samples: float = 0.0) -> np.ndarray:
    """H(t - t_index) (``width_samples`` 0), or a linear ramp from 0 to 1 over
    ``width_samples`` centred on it: a step, or the smooth change it is tested against."""
    if width_samples <= 0:
        shape = np.zeros(n)
        shape[index:] = 1.0
        return shape
    return np.clip((np.arange(n) - index) / width_samples + 0.5, 0.0, 1.0)
