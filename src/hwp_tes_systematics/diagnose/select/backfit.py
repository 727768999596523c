"""Backfitting: a set of effects with a nonlinear one (the time constant, by variable
projection), events (glitches, detected and fitted one by one) or the nonlinearity acting
on the other effects, fitted piece by piece until chi^2 settles (:mod:`.`, "Fitting a
set of effects"); and the screen that skips a nonlinear fit its linearised template
shows cannot pass. Each function takes the :class:`.bank.FitProblem` being fitted
(``problem``), whose ``fit`` calls them."""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize

from ..effects import SELECTION_THRESHOLD
from ..fourier import irfft
from ..linalg import cross, realify, solve_normal
from .results import Composition, EffectFit, FitResult

BACKFIT_PASSES = 4
# with the nonlinearity composed: its templates converge by ~2 g1 A_2 per rebuild
# (g1 A_2 = 0.04: 0.3 % of g1, then 0.02 %, ...) until the cross term is below
# Delta chi^2 = 0.01 (estimated ~6 passes from a cross term of ~1e4; the H3-402 tests at
# g1 A_2 = 0.04 converge within the eight)
COMPOSED_PASSES = 8
CONVERGED_CHI2 = 0.05  # backfitting stops when chi^2 changes by less than this
# the nonlinearity's first linear fit beside the other signal effects: a variance inflation
# of g1 above this (correlation above 0.995) means they share a line at first order (an
# HWPSS harmonic at 4 f_HWP takes the 4f line of g1 A_2^2 / 2), and only the composition
# (the cross terms g1 x 2 A_2 x the harmonic) tells the two apart: self-consistent
# solutions of each side, reached from fit_composed's three starts
DEGENERATE_INFLATION = 100.0
# with the nonlinearity composed, a rebuild that raises chi^2 by more than this above the
# lowest pass walks away from the minimum (along a direction the first-order templates
# share): the lowest pass is kept
CHI2_RISE = 1.0


def nonlinear_screen(problem, selected) -> FitResult | None:
    """Skip the fit of a nonlinear effect when even its linearised template cannot pass.

    With linear effects only besides it, the linearised effect (for tau the template
    -d d_nom/dt, exact to first order) is fitted beside them; if its Delta chi^2 is below
    half its BIC penalty plus |threshold|, it cannot be selected and the fit without it
    is returned (its parameter reported at the linearised value). A large tau, where
    the linearisation is poor, has a huge linearised Delta chi^2 and is fitted.
    """
    effect = problem.nonlinear_of(selected)
    if effect is None:
        return None
    name = effect.name
    (parameter,) = effect.parameters
    others = tuple(n for n in selected if n != name)
    if any(problem.effects[n].kind != "linear" for n in others) or problem.composed(selected):
        return None
    base = problem.fit(others)
    rows = problem.rows(others)
    delta, taus, sigmas = 0.0, [], []
    for k in range(problem.n_det):
        lin = problem.linearised_f[name][k][None, :]
        aug = np.vstack([lin, problem.bank[k][rows]]) if rows.size else lin
        gram = problem.gram_nom[k][np.ix_(rows, rows)] if rows.size else np.zeros((0, 0))
        full = np.zeros((rows.size + 1, rows.size + 1))
        full[1:, 1:] = gram
        full[0] = cross(lin, aug, problem.w_nom[k])[0]
        full[:, 0] = full[0]
        rhs = np.concatenate(
            [cross(lin, problem.residual_f[k], problem.w_nom[k]), problem.rhs_nom[k][rows]]
        )
        a, cov = solve_normal(full, rhs)
        chi2 = problem.yy_nom[k] - 2 * rhs @ a + a @ full @ a
        delta += base.chi2_per_detector[k] - chi2
        taus.append(a[0])
        sigmas.append(math.sqrt(max(cov[0, 0], 0.0)))
    if delta >= 0.5 * (problem.n_det * problem.ln_n_eff + abs(SELECTION_THRESHOLD)):
        return None
    effects = dict(base.effects)
    effects[name] = EffectFit(
        name, values={parameter: np.array(taus)}, sigmas={parameter: np.array(sigmas)}
    )
    return FitResult(
        selected=selected,
        chi2=base.chi2,
        chi2_per_detector=base.chi2_per_detector,
        n_params=base.n_params + problem.n_det,
        prior_penalty=base.prior_penalty,
        effects=effects,
        model_f=None,
    )


def fit_nonlinear(problem, effect, k, y, bank, gram, w, start):
    """Variable projection: the nonlinear ``effect``'s parameter theta by least_squares
    with the linear parameters profiled out, from its linearised solution.

    Returns (theta, sigma_theta, linear parameters, their covariance).
    """
    sw = np.sqrt(2.0 * w)
    if start is None:
        # the linearised solution: the effect's first-order template beside the others
        lin = problem.linearised_f[effect.name][k][None, :]
        aug = np.vstack([lin, bank]) if bank.shape[0] else lin
        a, _ = solve_normal(cross(aug, aug, w), cross(aug, y, w))
        start = float(a[0])
    start = float(np.clip(start, *effect.start_range))

    def residual(theta):
        r = y - problem.nonlinear_model(effect, k, theta[0])
        if bank.shape[0]:
            a, _ = solve_normal(gram, cross(bank, r, w))
            r = r - a @ bank
        return realify(r * sw)

    low, high = effect.bounds
    solution = scipy.optimize.least_squares(
        residual, [start], bounds=([low], [high]), x_scale=[max(start, 1e-4)], method="trf"
    )
    theta = float(solution.x[0])
    r = y - problem.nonlinear_model(effect, k, theta)
    a = solve_normal(gram, cross(bank, r, w))[0] if bank.shape[0] else np.zeros(0)
    jacobian = problem.nonlinear_model(effect, k, theta, derivative=True)[None, :]
    full = np.vstack([jacobian, bank]) if bank.shape[0] else jacobian
    _, cov = solve_normal(cross(full, full, w), np.zeros(full.shape[0]))
    return theta, math.sqrt(max(cov[0, 0], 0.0)), a, cov[1:, 1:]


def detect_events(problem, effect, k: int, r_f: np.ndarray, bank, gram) -> list:
    """The events of ``effect`` (glitches, readout steps) in the residual r_f (rfft) of
    detector k, kept when their own significance pays their BIC penalty (``effect.find``;
    ``bank`` and ``gram`` the linear templates fitted beside them and their Gram matrix)."""
    return effect.find(problem, k, r_f, bank=bank, gram=gram)


# relative gain drifts, d_obs = [1 + delta(t)] d, that may act before the nonlinearity
# (optical efficiency, the TES's responsivity) or after it (the readout's gain): a composed
# fit tries both (fit_composed); they differ by g1 delta d^2, a 4f line following the drift
READOUT_GAINS = ("gain_drift", "gain_drift_common")


def fit_iterative(problem, selected, initial_extra=None, gain_after=False) -> FitResult:
    """Backfitting of the linear, nonlinear (time constant) and events (glitches) parts
    (module docstring). ``initial_extra``: with the nonlinearity composed, the signal (per
    detector, time domain) its templates are first built on beside d_nom (None: d_nom
    alone; :func:`fit_composed` starts from three). A composed fit of linear effects
    carries what its nonlinearity acts on (:class:`.results.Composition`). ``gain_after``: a relative gain drift
    (READOUT_GAINS) acts after the nonlinearity, (1 + delta)(d + g1 d^2), as a readout
    gain does, rather than before it, D + g1 D^2 with D = (1 + delta) d: to first order in
    delta the nonlinearity is then composed on d + delta d / 2."""
    ctx = problem.ctx
    n_det = problem.n_det
    linear = [n for n in selected if n in problem.slices]
    rows = problem.rows(linear)
    nonlinear = problem.nonlinear_of(selected)
    events_effects = problem.events_of(selected)
    composed = problem.composed(selected)
    nl_rows = np.zeros(0, dtype=int)
    gain_rows = np.zeros(0, dtype=int)  # a relative gain drift's rows (gain_after)
    responses = []  # the response effects selected, in bank-row order
    if composed:
        position = problem.n_nominal
        for name in linear:
            width = problem.slices[name].stop - problem.slices[name].start
            if problem.effects[name].stage == "response":
                nl_rows = np.concatenate([nl_rows, np.arange(position, position + width)])
                responses.append(problem.effects[name])
            elif gain_after and name in READOUT_GAINS:
                gain_rows = np.concatenate([gain_rows, np.arange(position, position + width)])
            position += width
    # the events' rfft per detector, all events effects summed, and each effect's events
    events_f = [np.zeros(problem.freqs.size, complex) for _ in range(n_det)]
    events: dict[str, list] = {effect.name: [] for effect in events_effects}
    # each events effect's rfft per detector (with one effect: the sum itself, no copy)
    each_events_f = {
        effect.name: events_f
        if len(events_effects) == 1
        else [np.zeros(problem.freqs.size, complex) for _ in range(n_det)]
        for effect in events_effects
    }
    theta = [None] * n_det  # the nonlinear effect's parameter per detector
    theta_sigma = [0.0] * n_det
    values = [np.zeros(rows.size) for _ in range(n_det)]
    covariances = [np.zeros((rows.size, rows.size)) for _ in range(n_det)]
    models = [np.zeros(problem.freqs.size, complex) for _ in range(n_det)]
    # each detector's rows, a private copy (fancy indexing copies): a rebuild rewrites the
    # nonlinearity's rows in place, and used_nl keeps the rows its last fit used
    banks = [problem.bank[k][rows] for k in range(n_det)]
    recomposed = [False] * n_det  # the nonlinearity rows of banks[k] were recomputed
    built_on = [None] * n_det  # the extra signal they were recomputed with (None: none)
    used_nl = [banks[k][nl_rows] for k in range(n_det)]
    nonlinear_parts = [0.0] * n_det
    offsets = np.zeros(n_det)  # the offset taken out of each detector's extra signal
    first_pass_inflation = np.ones(n_det)  # the nonlinearity's variance inflation, pass 1
    grams = [None] * n_det  # each detector's Gram matrix of its last linear solve

    def rebuild(k, extra):
        """The nonlinearity's template rows of detector k built on d_nom + ``extra``."""
        recomposed[k] = True
        built_on[k] = extra
        banks[k][nl_rows] = problem.response_rows_f(k, extra, responses)

    if composed and initial_extra is not None:
        for k in range(n_det):
            rebuild(k, initial_extra[k])
    passes = COMPOSED_PASSES if composed else BACKFIT_PASSES if events_effects else 1
    previous_chi2 = math.inf
    lowest, kept = math.inf, None  # the composed passes' lowest chi^2 and its state
    for _ in range(passes):
        updated = False  # did the nonlinearity templates change in this pass?
        for k in range(n_det):
            w = problem.w_nom[k]
            bank = banks[k]
            gram = problem.gram_nom[k][np.ix_(rows, rows)]
            if recomposed[k]:  # else the precomputed block is exact
                gram[nl_rows] = cross(bank[nl_rows], bank, w)
                gram[:, nl_rows] = gram[nl_rows].T
            grams[k] = gram
            y = problem.residual_f[k] - events_f[k]
            if nonlinear is not None:
                theta[k], theta_sigma[k], a, cov = fit_nonlinear(
                    problem, nonlinear, k, y, bank, gram, w, theta[k]
                )
                m_nonlinear = problem.nonlinear_model(nonlinear, k, theta[k])
            else:
                a, cov = solve_normal(gram, cross(bank, y, w))
                m_nonlinear = 0.0
            values[k], covariances[k] = a, cov
            if composed and previous_chi2 == math.inf and nl_rows.size:
                g = nl_rows[0]  # marginal over conditional variance of g1 (1: no degeneracy)
                first_pass_inflation[k] = float(cov[g, g] * gram[g, g])
            used_nl[k], nonlinear_parts[k] = bank[nl_rows], m_nonlinear
            models[k] = (a @ bank if rows.size else 0.0) + m_nonlinear + events_f[k]
            if composed:  # the nonlinearity acts on d_nom + the other fitted effects
                model_f = models[k] - events_f[k]  # a bank + m_nonlinear
                # the model without the nonlinearity's own rows (no copy of the bank's rows)
                signal_f = model_f - a[nl_rows] @ bank[nl_rows]
                if gain_rows.size:  # a readout gain: half its drift before the nonlinearity
                    signal_f = signal_f - 0.5 * (a[gain_rows] @ bank[gain_rows])
                extra = irfft(signal_f, n=problem.n, workers=problem.workers)
                # and the offset before the nonlinearity: the adjusted offset matched the
                # recorded mean, which holds the model's mean (g1 <d^2> ~ g1 A_2^2 / 2);
                # left in, it makes 2 g1 O d, which the gain takes and rescales d^2 by
                # ~4 g1 O (0.3 % of g1 at g1 A_2 = 0.04). The DC mode is not fitted.
                offsets[k] = problem.valid_mean(k, model_f)
                extra -= offsets[k]
                # chi^2 of the cross term 2 g1 d_nom x (extra - the extra the templates
                # were last built with): skip the rebuild when negligible
                change = extra if built_on[k] is None else extra - built_on[k]
                sigma2 = problem.white_variance(k)
                g1 = a[nl_rows[0]]
                cross_chi2 = (
                    4
                    * g1**2
                    * float(np.sum((ctx.d_nom[k] * change * problem.valid[k]) ** 2))
                    / sigma2
                )
                if cross_chi2 < 0.01:
                    continue
                updated = True
                rebuild(k, extra)
        values, covariances, shared = problem.share(linear, values, covariances)
        if shared:
            for k in range(n_det):
                # the bank its fit used: the nonlinearity's rows as they were then
                since = values[k][nl_rows] @ (used_nl[k] - banks[k][nl_rows])
                models[k] = values[k] @ banks[k] + since + nonlinear_parts[k] + events_f[k]
        if events_effects:  # each sought in the residual without its own events
            for effect in events_effects:
                own = each_events_f[effect.name]
                found = []

                def residual_of(k, own=own, models=models):  # without these events
                    r_f = problem.residual_f[k] - models[k] + own[k]
                    return r_f, banks[k], problem.gram_nom[k][np.ix_(rows, rows)]

                for k in range(n_det):
                    found += detect_events(problem, effect, k, *residual_of(k))
                found = effect.complete_events(problem, found, residual_of)
                events[effect.name] = effect.detector_events(ctx, found)
                now = problem.masked_rfft(effect.events_tod(ctx, events[effect.name]))
                for k in range(n_det):
                    # the linear values given the new events (a step is fitted jointly
                    # with the linear templates and moves their values: the Schur
                    # complement); without it the model would hold the step alone
                    moved = 0.0
                    difference = own[k] - now[k]
                    if rows.size and grams[k] is not None and difference.any():
                        change = cross(banks[k], difference, problem.w_nom[k])
                        moved_nl = 0.0
                        if nl_rows.size:  # the bank its solve used: those rows as they were
                            change[nl_rows] = cross(used_nl[k], difference, problem.w_nom[k])
                        move = solve_normal(grams[k], change)[0]
                        if nl_rows.size:
                            moved_nl = move[nl_rows] @ (used_nl[k] - banks[k][nl_rows])
                        values[k] = values[k] + move
                        moved = move @ banks[k] + moved_nl
                    models[k] = models[k] - own[k] + now[k] + moved
                    own[k] = now[k]
            if len(events_effects) > 1:
                for k in range(n_det):
                    events_f[k] = sum(each_events_f[e.name][k] for e in events_effects)
            if shared:  # the moves were each detector's: shared again
                values, covariances, shared = problem.share(linear, values, covariances)
                for k in range(n_det):
                    since = values[k][nl_rows] @ (used_nl[k] - banks[k][nl_rows])
                    models[k] = values[k] @ banks[k] + since + nonlinear_parts[k] + events_f[k]
        if not (updated or events_effects):
            break
        total = sum(problem.chi2_of(k, models[k]) for k in range(n_det))
        if composed and total < lowest:  # the lowest pass's state, kept
            lowest = total
            kept = [
                list(x) if isinstance(x, list) else dict(x) if isinstance(x, dict) else x
                for x in (values, covariances, shared, models, used_nl)
                + (nonlinear_parts, theta, theta_sigma, events, events_f)
            ] + [{name: list(parts) for name, parts in each_events_f.items()}, offsets.copy()]
        elif composed and total > lowest + CHI2_RISE:  # walking away from it: back
            (values, covariances, shared, models, used_nl) = kept[:5]
            (nonlinear_parts, theta, theta_sigma, events, events_f) = kept[5:10]
            each_events_f, offsets = kept[10:12]
            break
        # while the nonlinearity's templates still move, chi^2 does not tell: it is
        # blind to the scale of d against g1 (g1 (1 + e)^2 d^2 with the gain taking
        # the linear part), which the rebuilds settle at the rate ~2 g1 A_2 per pass
        if abs(previous_chi2 - total) < CONVERGED_CHI2 and not updated:
            break
        previous_chi2 = total
    chi2s = np.array([problem.chi2_of(k, models[k]) for k in range(n_det)])
    fits = problem.with_shared(problem.linear_effect_fits(selected, values, covariances), shared)
    for k in range(n_det):  # the rows each detector's kept fit used
        banks[k][nl_rows] = used_nl[k]
    parts = problem.linear_parts(selected, banks, values)
    if nonlinear is not None:
        (parameter,) = nonlinear.parameters
        fits[nonlinear.name] = EffectFit(
            nonlinear.name,
            values={parameter: np.array(theta, dtype=float)},
            sigmas={parameter: np.array(theta_sigma)},
        )
        parts[nonlinear.name] = nonlinear_parts
    for effect in events_effects:
        fits[effect.name] = EffectFit(effect.name, events=events[effect.name])
        parts[effect.name] = list(each_events_f[effect.name])
    return FitResult(
        selected=selected,
        chi2=float(chi2s.sum()),
        chi2_per_detector=chi2s,
        n_params=problem.count_parameters(
            selected, {name: sum(e.n_parameters for e in found) for name, found in events.items()}
        ),
        prior_penalty=problem.prior_penalty(selected),
        effects=fits,
        model_f=models,
        parts=parts,
        first_pass_inflation=first_pass_inflation,
        gain_after=bool(gain_rows.size),
        composition=_composition(problem, rows, nl_rows, gain_rows, values, offsets)
        if composed and nonlinear is None
        else None,
    )


def _composition(problem, rows, nl_rows, gain_rows, values, offsets):
    """What the nonlinearity of a composed fit acts on (:class:`.results.Composition`): the
    fitted coefficients on the whole bank's rows, 0 on the nonlinearity's own and half on
    a readout gain's, as :func:`fit_iterative` composes them."""
    coefficients = []
    for k in range(problem.n_det):
        local = np.array(values[k], dtype=float)
        local[nl_rows] = 0.0
        local[gain_rows] *= 0.5
        full = np.zeros(problem.bank.shape[1])
        full[rows] = local
        coefficients.append(full)
    return Composition(coefficients=coefficients, offsets=offsets.copy())


def fit_composed(problem, selected) -> FitResult:
    """:func:`fit_iterative` of a set with the nonlinearity composed; with a relative gain
    drift in the set, fitted again with the drift after the nonlinearity (``gain_after``:
    a readout gain); where its first fit shares a line with the other signal effects
    (DEGENERATE_INFLATION), fitted again from the two starts that give the shared lines to
    one side (:func:`start_after`: the nonlinearity first, the signal effects first): the
    lowest chi^2 is the fit, the others its ``alternatives`` (each a minimum of its own,
    whose formal sigma does not cover the others)."""
    first = fit_iterative(problem, selected)
    if not problem.composed(selected):
        return first
    fits = [first]
    if any(name in READOUT_GAINS for name in selected):  # the drift before or after it
        fits.append(fit_iterative(problem, selected, gain_after=True))
    signal = [n for n in selected if n in problem.slices and problem.effects[n].stage == "signal"]
    inflation = first.first_pass_inflation
    if signal and inflation is not None and inflation.max() >= DEGENERATE_INFLATION:
        without_signal = tuple(n for n in selected if n not in signal)
        fits += [
            fit_iterative(problem, selected, initial_extra=start_after(problem, before, signal))
            for before in (without_signal, ())
        ]
    if len(fits) == 1:
        return first
    best, *others = sorted(fits, key=lambda fit: fit.chi2)
    for other in others:
        other.model_f = other.parts = None  # their parameters and chi^2 are what is kept
    best.alternatives = others
    return best


def start_after(problem, before, signal) -> list[np.ndarray]:
    """Per detector, the time-domain signal of the effects ``signal`` fitted on what the
    set ``before`` leaves (() : the nominal residual), as a composed fit's first signal:
    with ``before`` holding the nonlinearity, it has taken the lines it shares with them.
    Their mean over the valid samples is removed, as the composition's offset is."""
    base = problem.fit(before, keep_model=True) if before else None
    rows = np.concatenate(
        [np.arange(problem.slices[n].start, problem.slices[n].stop) for n in signal]
    )
    extras = []
    for k in range(problem.n_det):
        w = problem.w_nom[k]
        bank = problem.bank[k][rows]
        residual = problem.residual_f[k] - (base.model_f[k] if base is not None else 0.0)
        a, _ = solve_normal(problem.gram_nom[k][np.ix_(rows, rows)], cross(bank, residual, w))
        extra = irfft(a @ bank, n=problem.n, workers=problem.workers)
        extras.append(extra - float(np.mean(extra[problem.valid[k]])))
    if base is not None:
        base.model_f = base.parts = None  # as the cache keeps a fit (FitProblem.fit)
    return extras
