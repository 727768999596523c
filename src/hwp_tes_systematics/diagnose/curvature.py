"""Errors of a maximum-likelihood fit from the curvature of -2 ln L at its optimum.

The conditional error of a parameter, the others held, is sigma_i^2 = 2 / H_ii; the
marginal one, the others free, sigma_i^2 = 2 (H^-1)_ii, with H the Hessian of -2 ln L
(second differences of given steps). Both move their centre inside the parameters' bounds
by a step where the optimum sits on one (a correlation at 1).
"""

from __future__ import annotations

import math

import numpy as np


def curvature_sigmas(function, x, steps, bounds=None):
    """1-sigma of each parameter from the diagonal curvature of -2 ln L (sigma^2 = 2 / f''),
    the second difference of step h centred on x, or moved inside by h where x + h or
    x - h would leave ``bounds`` (a parameter at its bound, as rho = 1 for a gain common to
    the detectors: beyond it the pair's covariance is not positive)."""
    sigmas = []
    f_x = function(x)
    for i, h in enumerate(steps):
        lower, upper = bounds[i] if bounds is not None else (-math.inf, math.inf)
        centre = x.copy()
        centre[i] = min(max(x[i], lower + h), upper - h)
        f_centre = f_x if centre[i] == x[i] else function(centre)
        up, down = centre.copy(), centre.copy()
        up[i] += h
        down[i] -= h
        curvature = (function(up) - 2 * f_centre + function(down)) / h**2
        sigmas.append(math.sqrt(2.0 / curvature) if curvature > 0 else math.inf)
    return sigmas


def marginal_sigmas(function, x, steps, bounds):
    """1-sigma of each parameter marginalised over the others: sqrt(2 (H^-1)_ii) of the
    Hessian H of -2 ln L by central differences of step h, its centre moved inside the
    ``bounds`` by h where x sits within h of one; the conditional errors of
    :func:`curvature_sigmas` where H is not positive definite."""
    x = np.asarray(x, dtype=float)
    steps = np.asarray(steps, dtype=float)
    lower = np.array([b[0] for b in bounds]) + steps
    upper = np.array([b[1] for b in bounds]) - steps
    centre = np.clip(x, lower, upper)
    n = x.size
    hessian = np.empty((n, n))
    f_centre = function(centre)
    for i in range(n):
        for j in range(i, n):

            def at(di, dj, i=i, j=j):
                point = centre.copy()
                point[i] += di * steps[i]
                point[j] += dj * steps[j]
                return function(point)

            if i == j:
                value = (at(1, 0) - 2 * f_centre + at(-1, 0)) / steps[i] ** 2
            else:
                value = (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1)) / (4 * steps[i] * steps[j])
            hessian[i, j] = hessian[j, i] = value
    try:
        np.linalg.cholesky(hessian)
    except np.linalg.LinAlgError:
        return curvature_sigmas(function, x, steps, bounds)
    return [float(v) for v in np.sqrt(2.0 * np.diag(np.linalg.inv(hessian)))]
