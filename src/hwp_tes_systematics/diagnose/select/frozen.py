"""The screen of a candidate added to a composed fit (the nonlinearity acting on the other
effects, :func:`.backfit.fit_iterative`), or put in the place of one of its effects: the
candidate set fitted once, linearly, with the nonlinearity's templates held where the
current fit composed them (:func:`frozen_screen`).

A composed fit rebuilds the nonlinearity's templates (d^2, d^3) on d_nom plus the other
fitted effects until they settle, two or more fits of every detector and a template
rebuild between them; on a wafer most of a selection's time goes to the forward step's
candidates, most of which the data do not support. Held at the current fit's composition
(:class:`.results.Composition`), the set's fit is the linear one of :mod:`.bank` with the
nonlinearity's rows of the normal equations replaced by those of the rebuilt templates;
the candidate's Delta chi^2 over the current set, both fitted so, differs from the
composed fits' by what the candidate's own signal moves in the nonlinearity's templates
(2 g1 d x its model: second order in the small quantities). In a swap the templates also
hold the signal of the effect the candidate replaces, which its composed fit would not: the
held fit keeps the nonlinearity's response to that signal (2 g1 d x the replaced model,
real since the replaced effect was selected), so it fits the swap at least as well as the
composed fit to first order and its Delta BIC errs towards taking the swap. A nonlinear
candidate (the time constant) enters by its first-order template (``Effect.linearised_f``),
as :func:`.backfit.nonlinear_screen` fits it beside linear effects alone.
"""

from __future__ import annotations

import math

import numpy as np

from ..fourier import irfft
from ..linalg import cross, solve_normal
from .backfit import DEGENERATE_INFLATION
from .results import Composition, EffectFit, FitResult

# a candidate is screened out when its frozen Delta chi^2 is below this fraction of its
# BIC penalty (Delta k ln N_eff + its prior penalty; in a swap, when the frozen Delta BIC
# exceeds the rest of that penalty): the composed fit would have to find more than twice as
# much for it to pass, and the screened Delta BIC stays above 0, so it is neither selected
# nor a look-alike of the effect that is (explain.step.look_alikes)
SCREEN_FRACTION = 0.5


class FrozenRows:
    """The normal equations' rows of the response effects (the nonlinearity's d^p
    templates) rebuilt on d_nom + the signal the composed fit ``current`` holds, per
    detector: ``with_bank`` (n_response x bank rows), ``own`` (n_response x n_response)
    and ``with_residual`` (n_response), the same of each nonlinear effect's linearised
    template beside them (``linearised``, as one more row), and the current set's chi^2
    per detector so fitted."""

    def __init__(self, problem, current: FitResult):
        composition: Composition = current.composition
        self.composition = composition
        names = [n for n in problem.linear_names if problem.effects[n].stage == "response"]
        self.rows = np.concatenate(
            [np.arange(problem.slices[n].start, problem.slices[n].stop) for n in names]
        )
        self.with_bank, self.own, self.with_residual = [], [], []
        self.linearised: dict[str, list[tuple]] = {}
        for k in range(problem.n_det):
            spectrum = composition.coefficients[k] @ problem.bank[k]
            extra = irfft(spectrum, n=problem.n, workers=problem.workers) - composition.offsets[k]
            rebuilt = problem.response_rows_f(k, extra, [problem.effects[n] for n in names])
            w = problem.w_nom[k]
            self.with_bank.append(cross(rebuilt, problem.bank[k], w))
            self.own.append(cross(rebuilt, rebuilt, w))
            self.with_residual.append(cross(rebuilt, problem.residual_f[k], w))
            for name, rows in problem.linearised_f.items():
                row = rows[k][None, :]
                self.linearised.setdefault(name, []).append(
                    (
                        cross(row, problem.bank[k], w)[0],
                        cross(row, rebuilt, w)[0],
                        float(cross(row, row, w)[0, 0]),
                        float(cross(row, problem.residual_f[k], w)[0]),
                    )
                )
        self.current_chi2 = self.fit(problem, current.selected)[0]

    def fit(self, problem, selected) -> tuple:
        """(chi^2 per detector, values, covariances, shared, g1's largest variance
        inflation) of the effects ``selected`` with the response rows held (the linear fit
        of :mod:`.bank`); a nonlinear effect among them by its linearised template, its
        parameter last in the values."""
        rows = problem.rows([n for n in selected if n in problem.slices])
        nonlinear = problem.nonlinear_of(selected)
        local = np.flatnonzero(np.isin(rows, self.rows))  # the response rows' places
        which = np.searchsorted(self.rows, rows[local])
        solved, grams, rhss = [], [], []
        for k in range(problem.n_det):
            gram = problem.gram_nom[k][np.ix_(rows, rows)]
            rhs = problem.rhs_nom[k][rows]
            gram[local] = self.with_bank[k][which][:, rows]
            gram[:, local] = gram[local].T
            gram[np.ix_(local, local)] = self.own[k][np.ix_(which, which)]
            rhs[local] = self.with_residual[k][which]
            if nonlinear is not None:  # its linearised template, one more row
                with_bank, with_response, own, with_residual = self.linearised[nonlinear.name][k]
                column = with_bank[rows]
                column[local] = with_response[which]
                gram = np.block([[gram, column[:, None]], [column[None, :], np.array([[own]])]])
                rhs = np.append(rhs, with_residual)
            grams.append(gram)
            rhss.append(rhs)
            solved.append(solve_normal(gram, rhs))
        values, covariances, shared = problem.share(
            selected, [a for a, _ in solved], [cov for _, cov in solved]
        )
        chi2 = np.array(
            [
                problem.yy_nom[k] - 2 * rhss[k] @ values[k] + values[k] @ grams[k] @ values[k]
                for k in range(problem.n_det)
            ]
        )
        # g1's variance inflation, the largest over detectors (as backfit's first pass)
        g = local[0] if local.size else None
        inflation = max(
            (1.0 if g is None else float(covariances[k][g, g] * grams[k][g, g]))
            for k in range(problem.n_det)
        )
        return chi2, values, covariances, shared, inflation


def frozen_screen(problem, selected, current: FitResult) -> FitResult | None:
    """The candidate set ``selected`` (``current``'s set of linear effects with one more
    linear or nonlinear effect c, or with c in the place of one of them) when it cannot
    pass: fitted with the nonlinearity's templates held at ``current``'s composition
    (:class:`FrozenRows`), and the current set so too; if their Delta BIC exceeds
    (1 - SCREEN_FRACTION) of c's own penalty (for an added c: its Delta chi^2 is below
    SCREEN_FRACTION of its penalty), the result (chi^2 = chi^2(current) - that Delta
    chi^2, the frozen fit's parameters, ``screened``). None where the full composed fit is
    needed: the candidate may pass, it shares a line with the nonlinearity (g1's variance
    inflated DEGENERATE_INFLATION times: the full fit starts three ways), the current fit
    is not composed on linear effects (:class:`.results.Composition`), or the sets hold
    event effects (glitches, steps: their detection decides)."""
    composition = current.composition
    added = [n for n in selected if n not in current.selected]
    removed = [n for n in current.selected if n not in selected]
    if composition is None or len(added) != 1 or len(removed) > 1:
        return None
    if any(problem.effects[n].kind not in ("linear", "nonlinear") for n in selected):
        return None  # events: their detection decides
    frozen = problem.frozen_rows(current)
    chi2_current = frozen.current_chi2
    chi2, values, covariances, shared, inflation = frozen.fit(problem, selected)
    if inflation >= DEGENERATE_INFLATION:
        return None  # the candidate shares a line with the nonlinearity: the full fit's starts
    n_params = problem.count_parameters(selected, {})
    prior = problem.prior_penalty(selected)
    penalty = (n_params - current.n_params) * problem.ln_n_eff + prior - current.prior_penalty
    gain = float(np.sum(chi2_current) - np.sum(chi2))
    without = [n for n in selected if n not in added]  # c's own penalty
    own_penalty = (
        n_params - problem.count_parameters(without, {})
    ) * problem.ln_n_eff + problem.effects[added[0]].prior_penalty
    if not math.isfinite(gain) or penalty - gain <= (1 - SCREEN_FRACTION) * own_penalty:
        return None
    per_detector = current.chi2_per_detector - (chi2_current - chi2)
    effects = problem.with_shared(problem.linear_effect_fits(selected, values, covariances), shared)
    nonlinear = problem.nonlinear_of(selected)
    if nonlinear is not None:  # its linearised value, as backfit.nonlinear_screen reports it
        (parameter,) = nonlinear.parameters
        effects[nonlinear.name] = EffectFit(
            nonlinear.name,
            values={parameter: np.array([a[-1] for a in values])},
            sigmas={parameter: np.array([math.sqrt(max(c[-1, -1], 0.0)) for c in covariances])},
        )
    return FitResult(
        selected=selected,
        chi2=current.chi2 - gain,
        chi2_per_detector=per_detector,
        n_params=n_params,
        prior_penalty=prior,
        effects=effects,
        model_f=None,
        screened=True,
    )
