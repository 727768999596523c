"""The stepwise selection's moves on a problem whose chi^2 per set of effects is given
(no recording): what a late-offered effect may replace."""

from __future__ import annotations

import dataclasses

from hwp_tes_systematics.diagnose.select.stepwise import select_templates

LN_N = 10.0  # ln N_eff: each parameter costs 10 in the BIC
THRESHOLD = -10.0  # an effect enters when it lowers the BIC by more than 10


@dataclasses.dataclass
class Effect:
    name: str
    kind: str
    stage: str
    after_noise_refit: bool = False
    reported_as: None = None

    @property
    def family(self) -> str:
        return self.name

    def unphysical(self, params):
        return None


@dataclasses.dataclass
class Fit:
    selected: tuple
    chi2: float
    n_params: int
    screened: bool = False

    @property
    def effects(self) -> dict:
        return {name: {} for name in self.selected}

    def bic(self, ln_n: float) -> float:
        return self.chi2 + self.n_params * ln_n


class Problem:
    """chi^2 given per set of effects; each effect has 3 parameters."""

    ln_n_eff = LN_N

    def __init__(self, effects, chi2):
        self.effects = {e.name: e for e in effects}
        self.chi2 = {frozenset(k): v for k, v in chi2.items()}

    def fit(self, templates):
        return Fit(tuple(templates), self.chi2[frozenset(templates)], 3 * len(templates))

    def trial(self, templates, current):  # a candidate set: no screen here
        return self.fit(templates)


DRIFT = Effect("drift", "linear", "signal")
STEPS = Effect("steps", "events", "events", after_noise_refit=True)
# a step in the data: the drift, taken while steps were not offered, fits part of it;
# beside the drift a step adds little (598 from 600), alone it fits far better (400)
CHI2 = {(): 1000.0, ("drift",): 600.0, ("steps",): 400.0, ("drift", "steps"): 598.0}


def test_a_late_offered_effect_replaces_the_look_alike_chosen_before_it():
    """Offered after the first pass chose the drift, the step does not enter beside it
    (Delta BIC +28), but put in its place it lowers the BIC by 200: the swap step takes it."""
    steps: list = []
    selected = select_templates(
        Problem([DRIFT, STEPS], CHI2), ["steps"], THRESHOLD, 6, steps, initial=("drift",)
    )
    assert selected == ("steps",)
    assert steps[-1].note == "drift swapped for steps: a lower BIC"


def test_an_effect_offered_from_the_start_is_not_swapped_in():
    """The same effect not marked ``after_noise_refit`` (an events effect, offered with the
    others) is not tried in a linear effect's place: the drift stays."""
    early = dataclasses.replace(STEPS, after_noise_refit=False)
    selected = select_templates(
        Problem([DRIFT, early], CHI2), ["steps"], THRESHOLD, 6, [], initial=("drift",)
    )
    assert selected == ("drift",)


def test_a_swap_is_followed_by_a_backward_step():
    """After the step replaces the drift, an effect that only the drift needed (a
    harmonic: 3 parameters for chi^2 15 beside the step) leaves as redundant."""
    harmonic = Effect("harmonic", "linear", "signal")
    chi2 = {
        **CHI2,
        ("harmonic",): 900.0,
        ("drift", "harmonic"): 550.0,
        ("harmonic", "steps"): 395.0,
        ("drift", "harmonic", "steps"): 548.0,
    }
    steps: list = []
    selected = select_templates(
        Problem([DRIFT, STEPS, harmonic], chi2),
        ["steps"],
        THRESHOLD,
        6,
        steps,
        initial=("drift", "harmonic"),
    )
    assert set(selected) == {"steps"}
    assert [s.removed for s in steps if s.removed] == ["drift", "harmonic"]


class ScreeningProblem(Problem):
    """A screen that promises more than the full fit gives (a user's threshold above half a
    penalty lets a screened candidate lead the table)."""

    def __init__(self, effects, chi2, screened_chi2):
        super().__init__(effects, chi2)
        self.screened_chi2 = {frozenset(k): v for k, v in screened_chi2.items()}

    def trial(self, templates, current):
        chi2 = self.screened_chi2[frozenset(templates)]
        return Fit(tuple(templates), chi2, 3 * len(templates), screened=True)


def test_a_screened_candidate_that_leads_is_fitted_in_full_before_it_is_taken():
    """The screen puts the drift 100 below the nominal model, its full fit 10: the full fit
    decides (Delta BIC +20 against the threshold: nothing is selected)."""
    problem = ScreeningProblem(
        [DRIFT], {(): 1000.0, ("drift",): 990.0}, screened_chi2={("drift",): 900.0}
    )
    steps = []
    assert select_templates(problem, ["drift"], THRESHOLD, 3, steps) == ()
    assert steps[-1].candidates["drift"]["delta_bic"] == 20.0
    assert "screened" not in steps[-1].candidates["drift"]
