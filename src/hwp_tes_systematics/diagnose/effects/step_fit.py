"""The exact Whittle fit of a step's templates (H(t - i) x, x the valid samples for an
offset, the nominal signal for a gain) jointly with the linear templates fitted beside it
(a :class:`Bank`): at one position from the transforms (:func:`fit_templates`), at many
from one transform per part, its inner products moved from one sample to the next
(:func:`position_fits`), the change to the joint model made only for the position kept.
:mod:`.step_search` searches with it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..fourier import irfft, rfft
from ..linalg import cross, solve_normal
from .step_scan import edge_shape


@dataclass(frozen=True)
class Bank:
    """The linear templates fitted beside the steps, for one detector of ``n`` samples and
    weights ``w``: the selection's rfft rows (n_rows, nf; None for none), the recording's
    linear trend after them (its rfft, :func:`.step_scan.trend`), and the pseudo-inverse of
    their Gram matrix."""

    rows: np.ndarray | None
    trend_f: np.ndarray
    gram_inverse: np.ndarray
    w: np.ndarray
    n: int

    @classmethod
    def of(cls, rows, gram, trend_f: np.ndarray, w: np.ndarray, n: int) -> Bank:
        """The bank of ``rows`` (Gram matrix ``gram``; None or no rows: the trend alone)
        and the trend ``trend_f``, weights ``w``, ``n`` samples."""
        trend_trend = cross(trend_f[None], trend_f, w)
        if rows is None or gram is None or rows.shape[0] == 0:
            return cls(None, trend_f, solve_normal(trend_trend[None], np.zeros(1))[1], w, n)
        rows_trend = cross(rows, trend_f, w)
        full = np.block([[gram, rows_trend[:, None]], [rows_trend[None], trend_trend[None]]])
        return cls(rows, trend_f, solve_normal(full, np.zeros(full.shape[0]))[1], w, n)

    def products(self, x: np.ndarray) -> np.ndarray:
        """<B, x> for each template B of the bank (the trend last), x (nf,) or (k, nf):
        (n_templates,) or (n_templates, k), the weights applied to x (the smaller side)."""
        if x.ndim == 1:
            return np.concatenate([cross(b, x, self.w) for b in self._blocks])
        return np.concatenate([cross(x, b, self.w).T for b in self._blocks])

    def weighted_at(self, phases: np.ndarray) -> np.ndarray:
        """(K B)_t (:func:`weighted_at`) for each template B (the trend last) at the samples
        of ``phases`` (:func:`weighted_phases`): (n_templates, n_samples)."""
        return np.concatenate([weighted_at(b, phases) for b in self._blocks])

    @property
    def _blocks(self) -> list[np.ndarray]:
        """The rows and the trend (n_rows, nf) and (1, nf), without copying them together."""
        return [self.trend_f[None]] if self.rows is None else [self.rows, self.trend_f[None]]

    def combination(self, coefficients: np.ndarray) -> np.ndarray:
        """sum_B c_B B (rfft), the trend's coefficient last."""
        out = coefficients[-1] * self.trend_f
        return out if self.rows is None else out + coefficients[:-1] @ self.rows


def weighted_tod(x_f: np.ndarray, w: np.ndarray, n: int) -> np.ndarray:
    """(K x)_t = sum_f 2 w_f Re(X_f exp(2 pi i f t / n)) for the rfft X of x (n samples):
    the time-domain side of the Whittle product, <X, rfft(y)> = sum_t (K x)_t y_t. The
    inverse transform counts the zero and Nyquist frequencies once, the product twice."""
    doubled = np.array(w, dtype=float)
    doubled[0] *= 2.0
    if n % 2 == 0:
        doubled[-1] *= 2.0
    return n * irfft(doubled * x_f, n=n)


def weighted_phases(w: np.ndarray, n: int, samples: range) -> np.ndarray:
    """w_f exp(-2 pi i f t / n) at each of the consecutive ``samples``, as interleaved (Re,
    Im) reals (n_samples, 2 nf): one table lookup, then a product per sample."""
    frequencies = np.arange(w.size)
    roots = _roots_of_unity(n)
    current = w * roots[(frequencies * samples[0]) % n].conj()
    step = roots[frequencies % n].conj()
    out = np.empty((len(samples), w.size), dtype=complex)
    for m in range(len(samples)):
        out[m] = current
        current = current * step
    return out.view(np.float64)


def weighted_at(x_f: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """(K x)_t (:func:`weighted_tod`) at a few samples only, for each row of ``x_f`` (m,
    nf), from their :func:`weighted_phases` q*: (m, n_samples), one real product
    (Re(x q) = Re x Re q* + Im x Im q*)."""
    return 2.0 * (_interleaved(x_f) @ phases.T)


def _interleaved(x: np.ndarray) -> np.ndarray:
    """A complex array (..., nf) as interleaved reals (..., 2 nf) (a view where contiguous)."""
    return np.ascontiguousarray(x, dtype=complex).view(np.float64)


@functools.lru_cache(maxsize=2)
def _roots_of_unity(n: int) -> np.ndarray:
    """exp(2 pi i m / n), m = 0 .. n - 1."""
    return np.exp(2j * np.pi * np.arange(n) / n)


def position_fits(
    r_f: np.ndarray,
    w: np.ndarray,
    valid: np.ndarray,
    signal_k: np.ndarray,
    positions: list[int],
    bank: Bank | None,
    parts: tuple[str, ...],
) -> list[TemplateFit]:
    """The :class:`TemplateFit` of the step's ``parts`` at each of ``positions``
    (ascending), jointly with ``bank``, with one transform per part: the templates
    T_i = rfft(H(t - i) x) at the first position, then, leaving out each sample t before
    the next (T -> T - x_t rfft(e_t)), <T, Y> -> <T, Y> - x_t (K y)_t for the residual and
    each bank template (:func:`weighted_at`) and the Gram matrix by :func:`_gram_without`.
    The templates at a later position (:func:`_rows_moved`) are made only for the fit
    whose change is asked for."""
    n = valid.size
    shapes = np.stack([valid * 1.0 if part == "offset" else signal_k * valid for part in parts])
    rows = _edge_rows(shapes, positions[0])
    gram, rhs = cross(rows, rows, w), cross(rows, r_f, w)
    bank_r = bank_t = None
    if bank is not None:
        bank_r, bank_t = bank.products(r_f), bank.products(rows)  # (n_bank,), (n_bank, k)
    left_out = [t for t in range(positions[0], positions[-1]) if shapes[:, t].any()]
    if left_out:  # (K y)_t at the samples left out, for the residual and the bank
        phases = weighted_phases(w, n, range(left_out[0], left_out[-1] + 1))
        phases = phases[[t - left_out[0] for t in left_out]]
        at_r = weighted_at(r_f[None], phases)[0]
        at_bank = None if bank is None else bank.weighted_at(phases)
        kernel = _kernel(w, n)
    fits, m = [], 0  # m: the samples left out so far
    for i in positions:
        while m < len(left_out) and left_out[m] < i:
            x_t = shapes[:, left_out[m]]
            rhs = rhs - x_t * at_r[m]
            if bank is not None:
                bank_t = bank_t - np.outer(at_bank[:, m], x_t)
            gram = _gram_without(gram, shapes, left_out[m], kernel)
            m += 1
        fits.append(
            _solved(
                functools.partial(_rows_moved, rows, shapes, positions[0], i),
                gram,
                rhs,
                bank,
                bank_r,
                bank_t,
            )
        )
    return fits


_KERNELS: list[tuple[np.ndarray, int, np.ndarray]] = []  # (w, n, kernel), the latest few


def _kernel(w: np.ndarray, n: int) -> np.ndarray:
    """k = K e_0 (:func:`weighted_tod` of a unit impulse), kept for the last few weight
    arrays seen (each detector's search reuses its own; an array is matched by identity,
    and the cache holds it, so its identity is not reused)."""
    for cached_w, cached_n, kernel in _KERNELS:
        if cached_w is w and cached_n == n:
            return kernel
    kernel = weighted_tod(np.ones(w.size), w, n)
    _KERNELS.insert(0, (w, n, kernel))
    del _KERNELS[8:]
    return kernel


def _rows_moved(rows: np.ndarray, shapes: np.ndarray, first: int, i: int) -> np.ndarray:
    """The templates at position i from those at ``first`` (``rows``): T_i = T_first -
    sum_{first <= t < i} x_t exp(-2 pi i f t / n), no transform."""
    n = shapes.shape[-1]
    frequencies = np.arange(rows.shape[-1])
    moved = rows
    for t in range(first, i):
        if shapes[:, t].any():
            moved = moved - np.outer(shapes[:, t], _roots_of_unity(n)[frequencies * t % n].conj())
    return moved


def _edge_rows(shapes: np.ndarray, i: int) -> np.ndarray:
    """rfft(H(t - i) x) for each row x of ``shapes``."""
    return rfft(shapes * edge_shape(shapes.shape[-1], i))


def _gram_without(gram: np.ndarray, shapes: np.ndarray, t: int, kernel: np.ndarray):
    """<T_a, T_b> of the templates u_a = H(s - t) x_a after sample t is left out
    (u -> u - x_t e_t, K symmetric): G - x_t (K u)_t^T - (K u)_t x_t^T + x_t x_t^T k_0,
    with (K u)_t = sum_{s >= t} k_{s - t} x_s and k = K e_0 the kernel."""
    x_t = shapes[:, t]
    ku_t = shapes[:, t:] @ kernel[: shapes.shape[-1] - t]
    return gram - np.outer(x_t, ku_t) - np.outer(ku_t, x_t) + kernel[0] * np.outer(x_t, x_t)


class TemplateFit(NamedTuple):
    """A Whittle fit of step templates T jointly with a :class:`Bank`: its delta chi^2,
    values and covariance; :meth:`change_f` the rfft of the change it makes to the joint
    model, computed only where it is asked for (one fit of the many positions tried)."""

    delta_chi2: float
    values: np.ndarray
    covariance: np.ndarray
    templates: Callable[[], np.ndarray]  # T (rfft rows), made on demand
    bank: Bank | None
    projection: np.ndarray | None  # G^+ <B, T>

    def change_f(self) -> np.ndarray:
        """T values, the bank's coefficients moved by -G^+ <B, T> values."""
        change_f = self.values @ self.templates()
        if self.bank is not None:
            change_f = change_f - self.bank.combination(self.projection @ self.values)
        return change_f


def fit_templates(templates, r_f, w, bank: Bank | None) -> TemplateFit:
    """The Whittle fit of ``templates`` (rfft rows) jointly with ``bank``."""
    gram, rhs = cross(templates, templates, w), cross(templates, r_f, w)
    if bank is None:
        return _solved(lambda: templates, gram, rhs, None)
    return _solved(lambda: templates, gram, rhs, bank, bank.products(r_f), bank.products(templates))


def _solved(templates, gram, rhs, bank: Bank | None, bank_r=None, bank_t=None) -> TemplateFit:
    """The fit of the ``templates`` (made on demand) from their Gram matrix and <T, R>,
    projected off ``bank`` (``bank_r`` = <B, R>, ``bank_t`` = <B, T>): the Schur complement
    G_T - <T, B> G_B^+ <B, T>, b_T - <T, B> G_B^+ <B, R>."""
    projection = None
    if bank is not None:
        projection = bank.gram_inverse @ bank_t
        gram = gram - bank_t.T @ projection
        rhs = rhs - projection.T @ bank_r
    values, covariance = solve_normal(gram, rhs)
    return TemplateFit(float(values @ rhs), values, covariance, templates, bank, projection)
