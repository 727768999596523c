"""The selection (:func:`stepwise`): effects added by the BIC, removed when later ones make
them redundant, swapped for look-alikes that fit better (:mod:`.`, "StepwiseResult")."""

from __future__ import annotations

from dataclasses import dataclass

from .bank import DELTA_BIC_THRESHOLD, FitProblem
from .results import FitResult


@dataclass
class Step:
    """One step of the selection: an effect added, removed or swapped."""

    step: int
    added: str | None
    removed: str | None
    chi2_before: float
    chi2_after: float
    bic_before: float
    bic_after: float
    n_params_after: int
    candidates: dict[str, dict]  # name -> {"delta_chi2", "delta_bic"}
    note: str = ""

    @property
    def delta_chi2(self) -> float:
        return self.chi2_after - self.chi2_before

    @property
    def delta_bic(self) -> float:
        return self.bic_after - self.bic_before

    def as_dict(self) -> dict:
        return {
            "step": self.step,
            "added": self.added,
            "removed": self.removed,
            "chi2_before": self.chi2_before,
            "chi2_after": self.chi2_after,
            "delta_chi2": self.delta_chi2,
            "bic_before": self.bic_before,
            "bic_after": self.bic_after,
            "delta_bic": self.delta_bic,
            "n_params_after": self.n_params_after,
            "candidates": self.candidates,
            "note": self.note,
        }


@dataclass
class StepwiseResult:
    """Outcome of the stepwise selection."""

    baseline: FitResult
    final: FitResult
    steps: list[Step]
    ln_n_eff: float
    n_eff: int
    threshold: float
    delta_chi2: dict[str, float]  # effect -> chi^2(final without it) - chi^2(final)
    delta_bic: dict[str, float]  # effect -> BIC(final) - BIC(final without it)  (< 0)

    @property
    def ranked(self) -> list[str]:
        """Selected effects, most important first (largest drop-one Delta chi^2)."""
        return sorted(self.final.selected, key=lambda n: -self.delta_chi2[n])


def _change(current, after, ln_n, **extra) -> dict:
    """A step's candidate entry: Delta chi^2 and Delta BIC from ``current`` to ``after``."""
    return {
        "delta_chi2": after.chi2 - current.chi2,
        "delta_bic": after.bic(ln_n) - current.bic(ln_n),
        **extra,
    }


def _step(steps, current, after, ln_n, candidates, added=None, removed=None, note=""):
    steps.append(
        Step(
            step=len(steps) + 1,
            added=added,
            removed=removed,
            chi2_before=current.chi2,
            chi2_after=after.chi2,
            bic_before=current.bic(ln_n),
            bic_after=after.bic(ln_n),
            n_params_after=after.n_params,
            candidates=candidates,
            note=note,
        )
    )


def _backward(problem, templates, current, threshold, removed_sets, steps, keep=1):
    """Remove the effects that the others made redundant (BIC rises by < |threshold|).

    Stops at ``keep`` effects (1 after a forward step; 0 when checking a start set).
    """
    ln_n = problem.ln_n_eff
    while len(templates) > keep:
        removals = {n: problem.fit(tuple(m for m in templates if m != n)) for n in templates}
        costs = {n: r.bic(ln_n) - current.bic(ln_n) for n, r in removals.items()}
        weakest = min(costs, key=costs.get)
        reduced = frozenset(m for m in templates if m != weakest)
        if costs[weakest] >= -threshold or reduced in removed_sets:
            break
        removed_sets.add(reduced)
        after = removals[weakest]
        _step(
            steps,
            current,
            after,
            ln_n,
            {weakest: {"delta_chi2": after.chi2 - current.chi2, "delta_bic": -costs[weakest]}},
            removed=weakest,
            note=f"{weakest} made redundant by the other effects",
        )
        templates = tuple(m for m in templates if m != weakest)
        current = after
    return templates, current


def select_templates(problem, names, threshold, max_effects, steps: list, initial=()):
    """Forward selection with backward elimination of the template effects ``names``.

    ``initial``: effects to start from (a previous selection, checked first by the
    backward step), instead of the nominal model alone.
    """
    ln_n = problem.ln_n_eff
    templates: tuple = tuple(initial)
    current = problem.fit(templates)
    removed_sets: set = set()
    if templates:
        _step(
            steps,
            problem.fit(()),
            current,
            ln_n,
            {},
            note=f"noise refitted: start again from {list(templates)}",
        )
        templates, current = _backward(
            problem, templates, current, threshold, removed_sets, steps, keep=0
        )
    while len({problem.effects[n].family for n in templates}) < max_effects:
        remaining = [
            n
            for n in names
            if n not in templates and frozenset(templates + (n,)) not in removed_sets
        ]
        if not remaining:
            break
        trials = {n: problem.trial(templates + (n,), current) for n in remaining}
        table = {n: _candidate(problem, current, n, trial) for n, trial in trials.items()}
        best = _best(table)
        while best is not None and trials[best].screened and table[best]["delta_bic"] < threshold:
            # a threshold above half a penalty: the screen decides nothing, the full fit does
            trials[best] = problem.fit(templates + (best,))
            table[best] = _candidate(problem, current, best, trials[best])
            best = _best(table)
        if best is None or table[best]["delta_bic"] >= threshold:
            _step(steps, current, current, ln_n, table, note="no candidate passes the threshold")
            break
        _step(steps, current, trials[best], ln_n, table, added=best)
        templates += (best,)
        current = problem.fit(templates)  # the trial's fit (cached: a passing one is not screened)
        templates, current = _backward(problem, templates, current, threshold, removed_sets, steps)
    swapped, current = _swap_look_alikes(problem, names, templates, current, steps)
    if swapped != templates:  # what the newcomer explains may make another redundant
        swapped, current = _backward(problem, swapped, current, threshold, removed_sets, steps)
    templates = _one_family_for_a_line(problem, swapped, current, threshold, steps)
    return _without_unphysical(problem, templates, steps)


def _candidate(problem, current, name, trial) -> dict:
    """A forward step's table entry for the candidate ``name``: its changes (:func:`_change`),
    whether it was screened, and why its parameters are unphysical (an effect with
    unphysical parameters is not taken; a screen's are not judged)."""
    entry = _change(current, trial, problem.ln_n_eff)
    if trial.screened:
        entry["screened"] = True
    elif (why := problem.effects[name].unphysical(trial.effects[name])) is not None:
        entry["unphysical"] = why
    return entry


def _best(table) -> str | None:
    """The candidate of lowest Delta BIC among those with physical parameters, or None."""
    allowed = [n for n in table if "unphysical" not in table[n]]
    return min(allowed, key=lambda n: table[n]["delta_bic"]) if allowed else None


def _without_unphysical(problem, templates, steps) -> tuple:
    """Remove, one at a time, a selected effect whose parameters the final fit puts outside
    its physical bounds (``Effect.unphysical``): what it absorbed is left to the other
    effects or to ``unexplained``, not reported as its physics."""
    ln_n = problem.ln_n_eff
    current = problem.fit(templates)
    while (out := _first_unphysical(problem, templates, current)) is not None:
        name, why = out
        templates = tuple(t for t in templates if t != name)
        after = problem.fit(templates)
        _step(
            steps,
            current,
            after,
            ln_n,
            {name: _change(current, after, ln_n, unphysical=why)},
            removed=name,
            note=f"{name} removed: its parameters are outside physical bounds ({why})",
        )
        current = after
    return templates


def _first_unphysical(problem, templates, fit) -> tuple[str, str] | None:
    """(name, why) of the first effect of ``templates`` whose parameters in ``fit`` are
    outside its physical bounds, or None."""
    for name in templates:
        if name in fit.effects:
            why = problem.effects[name].unphysical(fit.effects[name])
            if why is not None:
                return name, why
    return None


def _swappable(effect) -> bool:
    return effect.kind == "linear" and effect.stage == "signal"


def _can_replace(effect) -> bool:
    """An unselected effect tried in a selected one's place: a linear signal effect, or
    one offered only once the noise is refitted (``Effect.after_noise_refit``: a readout
    step), which the selection's first choices were made without."""
    return _swappable(effect) or effect.after_noise_refit


def _swap_look_alikes(problem, names, templates, current, steps):
    """Replace a selected effect by an unselected one when that lowers the BIC.

    Forward selection never revisits a choice: the effect taken first (with the noise
    weights of that moment) stays even when a look-alike fits better once the noise is
    refitted or the other effects are in, e.g. an HWP temperature drift taken before a
    gain drift whose dipole drift shows only with the refitted 1/f noise, or a gain drift
    taken for a gain step before steps were offered. Tried for the linear signal effects
    (cheap fits) and, in their place, the effects offered after the noise refit; each
    swap is a step naming what it replaced (a backward step follows in select_templates).
    """
    ln_n = problem.ln_n_eff
    seen = {frozenset(templates)}
    while True:
        best = None
        trials = _swap_trials(problem, names, templates, current, seen, screen=True)
        for out, candidate, trial, gain in trials:
            if gain < 0 and (best is None or gain < best[3]):
                best = (out, candidate, trial, gain)
        if best is None:
            return templates, current
        out, candidate, trial, gain = best
        _step(
            steps,
            current,
            trial,
            ln_n,
            {candidate: _change(current, trial, ln_n)},
            added=candidate,
            removed=out,
            note=f"{out} swapped for {candidate}: a lower BIC",
        )
        templates = tuple(t for t in templates if t != out) + (candidate,)
        seen.add(frozenset(templates))
        current = trial


def _swap_trials(problem, names, templates, current, seen=frozenset(), screen=False):
    """(out, candidate, trial fit, BIC(trial) - BIC(current)) for each selected linear
    signal effect ``out`` and each unselected one of ``names`` put in its place, whose fit
    is physical; sets in ``seen`` are not fitted again. With ``screen``, a swap the screen
    shows cannot lower the BIC (:meth:`.bank.FitProblem.trial`) is left out."""
    ln_n = problem.ln_n_eff
    for out in [n for n in templates if _swappable(problem.effects[n])]:
        kept = tuple(t for t in templates if t != out)
        for candidate in names:
            if candidate in templates or not _can_replace(problem.effects[candidate]):
                continue
            if frozenset(kept + (candidate,)) in seen:
                continue
            if screen:
                trial = problem.trial(kept + (candidate,), current)
                if trial.screened:
                    continue
            else:
                trial = problem.fit(kept + (candidate,))
            if problem.effects[candidate].unphysical(trial.effects[candidate]):
                continue
            yield out, candidate, trial, trial.bic(ln_n) - current.bic(ln_n)


def final_swap_margins(problem, final) -> dict[str, dict[str, float]]:
    """{selected: {alternative: BIC(alternative in its place) - BIC(final)}} for each
    selected linear signal effect of the ``final`` fit and each unselected one of the
    catalog whose fit in its place is physical, under ``problem``'s noise weights: > 0 the
    data prefer the selected effect by that much. Full fits (the swap step's cached, the
    ones its screen left out fitted now), so that recordings diagnosed in parts compare
    margins of one kind."""
    margins: dict[str, dict[str, float]] = {
        out: {} for out in final.selected if _swappable(problem.effects[out])
    }
    for out, candidate, _, gain in _swap_trials(
        problem, list(problem.effects), final.selected, final
    ):
        margins[out][candidate] = float(gain)
    return margins


def _one_family_for_a_line(problem, templates, current, threshold, steps):
    """Mechanism parsimony: when a family found line by line (``Effect.reported_as``: the
    HWPSS harmonics) is among the selected effects, an effect whose lines one more member
    of that family fits as well (chi^2 within |threshold|) is replaced by it.

    E.g. lines at f_HWP and at 4 f_HWP, the 4f line in phase with twice the 2f phase and
    no 2 f_HWP +- f_spin sidebands: the nonlinearity fits the 4f line with one parameter
    per detector where the harmonic needs two, but with the harmonics already present
    "two HWPSS lines" is one mechanism where "a line and a nonlinearity" is two. A
    nonlinearity whose sidebands are seen is kept (replacing it raises chi^2 by more).
    """
    ln_n = problem.ln_n_eff
    while True:
        families = {problem.effects[n].reported_as for n in templates} - {None}
        members = [
            m
            for m, e in problem.effects.items()
            if e.reported_as in families and m not in templates
        ]
        others = [n for n in templates if problem.effects[n].reported_as is None]
        best = None
        for name in others:
            kept = tuple(t for t in templates if t != name)
            for member in members:
                trial = problem.fit(kept + (member,))
                if trial.chi2 - current.chi2 < -threshold and (
                    best is None or trial.chi2 < best[2].chi2
                ):
                    best = (name, member, trial)
        if best is None:
            return templates
        name, member, trial = best
        _step(
            steps,
            current,
            trial,
            ln_n,
            {member: _change(current, trial, ln_n)},
            added=member,
            removed=name,
            note=f"{name} replaced by {member}: one family explains the lines as well",
        )
        templates = tuple(t for t in templates if t != name) + (member,)
        current = trial


def stepwise(
    problem: FitProblem,
    delta_bic_threshold: float = DELTA_BIC_THRESHOLD,
    max_effects: int = 6,
    candidates=None,
    initial=(),
) -> StepwiseResult:
    """Forward stepwise selection over the catalog with the BIC (module docstring).

    ``initial``: start from these effects (checked by a backward step first).
    """
    ln_n = problem.ln_n_eff
    names = list(problem.effects) if candidates is None else list(candidates)
    names = [n for n in names if n in problem.effects]
    steps: list[Step] = []
    baseline = problem.fit(())
    templates = select_templates(problem, names, delta_bic_threshold, max_effects, steps, initial)
    final = problem.fit(templates)
    delta_chi2, delta_bic = {}, {}
    for name in final.selected:
        without = problem.fit(tuple(n for n in final.selected if n != name))
        delta_chi2[name] = without.chi2 - final.chi2
        delta_bic[name] = final.bic(ln_n) - without.bic(ln_n)
    return StepwiseResult(
        baseline=baseline,
        final=final,
        steps=steps,
        ln_n_eff=ln_n,
        n_eff=problem.n_eff,
        threshold=delta_bic_threshold,
        delta_chi2=delta_chi2,
        delta_bic=delta_bic,
    )
