"""Step 3 of the diagnosis: the catalog's effects the BIC keeps, fitted jointly (:class:`Selection`)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..effects import noise_effect
from ..nominal.adjustments import NOMINAL, refit_noise
from ..nominal.step import NominalFit
from .bank import FitProblem
from .stepwise import final_swap_margins, stepwise

log = logging.getLogger(__name__)

NOISE_REFIT_CHANGE = 0.02  # select again when the noise PSD at the effects moved by > 2 %


@dataclasses.dataclass
class Selection:
    """Step 3 (:func:`select_effects`): the effects the BIC keeps, fitted jointly."""

    problem: FitProblem  # the template bank and normal equations of the last pass
    steps: object  # fit.stepwise's result of the last pass (ranked, delta_chi2, ...)
    final: object  # the joint fit of the selected effects
    history: list  # every step of every pass
    fluctuation: object  # the fitted excess noise (noise_effect("excess").fit_noise) or None
    rolloff: object  # the noise's roll-off beside the effects (noise_effect("rolloff").fit_noise)
    # the pairs' coupling in the final residual (noise_effect("correlation").fit_noise), or
    # None for one detector
    crosstalk: object
    noise_models: list  # the noise of the final fit
    residual_after: np.ndarray  # (n_det, n_samples) the residual less the final fit [K]
    partial: dict  # {effect: the residual with that effect alone put back}
    # per selected linear signal effect, {look-alike: BIC in its place - BIC(final)}
    swap_margins: dict


def _takes_fluctuation(trial, selected, fitted_fluctuation, noise, threshold) -> bool:
    """Do the effects ``selected`` (the first pass's and the held-out ones that entered
    under the noise without a fluctuation) take the fluctuation's power? The fluctuation
    fitted on the residual without them (``noise`` the noise without it) no longer passes.
    Where it still passes, the held-out effects entered on the power the fluctuation
    explains (a common gain fluctuation is a string of coincident gain steps to a step
    search run under a noise without its sidebands)."""
    fit = trial.fit(selected, keep_model=True)
    remaining_f = trial.residual_f - np.array(fit.model_f)
    return fitted_fluctuation(remaining_f, noise).delta_bic >= threshold


def select_effects(
    fit: NominalFit, delta_bic_threshold: float, max_effects: int, workers: int, progress
) -> Selection:
    """Step 3: the catalog's effects selected stepwise by the BIC, jointly with the
    adjustments (:func:`.select.stepwise`). The noise was fitted before any effect was
    removed, and a strong effect leaks power beyond its line bins: it is refitted on the
    residual of the best fit and, if it moved by more than NOISE_REFIT_CHANGE where the
    effects are, or a gain fluctuation (:mod:`.fluctuations`, an excess noise in the 2f
    sidebands) is taken into it, the selection runs again with the new weights, starting
    from the effects found. An effect marked ``after_noise_refit`` (an event search, which
    finds false events where the first noise misses power) is offered from that second
    pass, which then always runs; if it enters, the noise is refitted once more and a
    third pass checks the selection (what the first pass's effects took of it). When a
    gain fluctuation would be taken after the first pass, the held-out effects are first
    offered under the noise refitted without it (a gain step's power in the 2f sidebands
    passes for a fluctuation's); where the fluctuation fitted on the residual without
    what entered no longer passes, all effects are selected again under that noise and
    the fluctuation is fitted again on that residual, else the held-out effects wait
    for the second pass. Then the
    fluctuation and the noise's roll-off are fitted again beside the final effects, and
    the pairs' crosstalk on the final residual (:mod:`..effects.crosstalk`). Updates
    ``fit.adjusted.noise``."""
    ctx, adjusted, nominal = fit.context, fit.adjusted, fit.nominal
    noise_models = fit.noise_models
    previous = ()
    history = []
    fluctuation = None
    problem = FitProblem(
        ctx,
        fit.recording.tod,
        noise_models,
        workers=workers,
        nominal=NOMINAL,
        residual_f=fit.residual_f,
    )
    # effects sought only under the refitted noise: offered from the second pass, which
    # then always runs (on the first pass's weights if the noise did not move); when one
    # enters, the noise is refitted without it in the residual and a third pass checks
    held_out = [n for n, e in problem.effects.items() if e.after_noise_refit]
    noise_changed = False  # by the last pass's refit

    def select(candidates, initial, on=None):
        result = stepwise(
            on or problem,
            delta_bic_threshold=delta_bic_threshold,
            max_effects=max_effects,
            candidates=candidates,
            initial=initial,
        )
        history.extend(result.steps)
        return result

    def fitted_fluctuation(remaining_f, noise):  # (the modes do not depend on the weights)
        return noise_effect("excess").fit_noise(
            ctx, remaining_f, noise, problem.modes, problem.ln_n_eff, also_from=nominal
        )

    for attempt in range(3):
        if noise_changed:  # same templates and residual, new noise weights
            problem = problem.with_noise(noise_models)
        note = ", noise refitted" if noise_changed else ", the held-out effects offered"
        progress("selecting effects (pass %d%s)", attempt + 1, note if attempt else "")
        if not attempt:
            steps = select([n for n in problem.effects if n not in held_out], previous)
        elif noise_changed:
            steps = select(list(problem.effects), previous)
        else:  # the same weights: pass 1's candidates fail again unless a held-out one enters
            steps = select(held_out, previous)
            if set(steps.final.selected) != set(previous):
                steps = select(list(problem.effects), steps.final.selected)
        final = problem.fit(steps.final.selected, keep_model=True)
        log.debug("selected: %s", ", ".join(final.selected) or "nothing")
        late = any(n in final.selected for n in held_out)
        if attempt == 2 or (attempt == 1 and (not late or fluctuation is not None)):
            break
        previous = final.selected  # checked first in the next pass, then extended
        remaining_f = problem.residual_f - np.array(final.model_f)
        noise_changed = False
        if not attempt:
            fluctuation = fitted_fluctuation(remaining_f, noise_models)
            if fluctuation.delta_bic < delta_bic_threshold and held_out:
                # a step's power in the 2f sidebands passes for a gain fluctuation's (a bias
                # line's gain step, the rest of a slow modulation fitted to it): the held-out
                # effects are first offered under the noise refitted without a fluctuation
                refit, covariances, _ = refit_noise(ctx, remaining_f, noise_models)
                trial = problem.with_noise(refit)
                progress("selecting effects (the held-out effects, before a gain fluctuation)")
                steps = select(held_out, previous, on=trial)
                if set(steps.final.selected) != set(previous) and _takes_fluctuation(
                    trial, steps.final.selected, fitted_fluctuation, refit, delta_bic_threshold
                ):  # one entered and took the fluctuation's power: all again
                    steps = select(list(problem.effects), steps.final.selected, on=trial)
                    problem, noise_models = trial, refit
                    adjusted.noise, adjusted.noise_covariance = refit, covariances
                    final = problem.fit(steps.final.selected, keep_model=True)
                    previous = final.selected
                    remaining_f = problem.residual_f - np.array(final.model_f)
                    fluctuation = fitted_fluctuation(remaining_f, noise_models)
            if fluctuation.delta_bic < delta_bic_threshold:
                noise_models, noise_changed = fluctuation.noise, True
                adjusted.noise = fluctuation.base_noise
                continue
            fluctuation = None
        if final.selected:
            refit, covariances, change = refit_noise(ctx, remaining_f, noise_models)
            if change >= NOISE_REFIT_CHANGE:
                noise_models, noise_changed = refit, True
                adjusted.noise, adjusted.noise_covariance = refit, covariances
        if not noise_changed and (attempt or not held_out):
            break
    remaining_f = problem.residual_f - np.array(final.model_f)  # of the final fit

    def fluctuation_beside(noise):  # with the detectors' coherence where it is taken
        return noise_effect("excess").fit_noise(
            ctx,
            remaining_f,
            noise,
            problem.modes,
            problem.ln_n_eff,
            also_from=nominal,
            coherence_below=delta_bic_threshold,
        )

    if fluctuation is not None:  # its parameters on the final residual
        fluctuation = fluctuation_beside(fluctuation.base_noise)
        if fluctuation.delta_bic < delta_bic_threshold:
            noise_models = fluctuation.noise
            adjusted.noise = fluctuation.base_noise
        else:  # what it took is explained by the effects selected since
            fluctuation = None
    residual_after = problem.residual_after(final)
    partial = problem.partial_residuals(final)
    # the time constant's one signature the lines lack: the noise's roll-off (:mod:`.rolloff`)
    rolloff = noise_effect("rolloff").fit_noise(
        ctx,
        remaining_f,
        noise_models,  # with a fitted fluctuation's sidebands, held
        problem.modes,
        problem.ln_n_eff,
    )
    if rolloff.delta_bic >= delta_bic_threshold and any(
        getattr(m, "base", m).tau_s > 0 for m in noise_models
    ):
        # the early roll-off is not confirmed beside the effects and a fluctuation's sidebands
        # (whose wings fall away from 2 f_HWP as a pole does): the noise loses its pole, and a
        # fitted fluctuation is fitted again beside the noise without it
        noise_models = rolloff.noise_without
        adjusted.noise = [getattr(m, "base", m) for m in noise_models]
        if fluctuation is not None:
            fluctuation = fluctuation_beside(adjusted.noise)
            if fluctuation.delta_bic < delta_bic_threshold:
                noise_models = fluctuation.noise
                adjusted.noise = fluctuation.base_noise
            else:  # the pole's wings were what it took: neither is kept
                fluctuation = None
    crosstalk = None
    if ctx.n_detectors > 1:  # the residuals' correlation, with the final noise
        crosstalk = noise_effect("correlation").fit_noise(
            ctx,
            remaining_f,
            noise_models,
            problem.modes,
            problem.ln_n_eff,
            threshold=delta_bic_threshold,
        )
    return Selection(
        problem,
        steps,
        final,
        history,
        fluctuation,
        rolloff,
        crosstalk,
        noise_models,
        residual_after,
        partial,
        final_swap_margins(problem, final),  # the last pass's noise weights
    )
