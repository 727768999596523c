"""What a fit gives: the fitted parameters of each effect and the fit of a set of effects."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..effects import GlitchEvent, StepEvent


@dataclass
class EffectFit:
    """Fitted parameters of one effect: per-detector values and 1-sigma uncertainties."""

    name: str
    values: dict[str, np.ndarray] = field(default_factory=dict)  # parameter -> (n_det,)
    sigmas: dict[str, np.ndarray] = field(default_factory=dict)
    events: list[GlitchEvent | StepEvent] = field(default_factory=list)
    # a shared effect (``Effect.shared``): its common parameters (per group, {label:
    # {parameter: value}}, for one shared by group, ``Effect.group_by``), and the chi^2 that
    # sharing them costs against a separate fit per detector, for sharing_dof fewer parameters
    shared_values: dict[str, float] = field(default_factory=dict)
    shared_sigmas: dict[str, float] = field(default_factory=dict)
    group_values: dict[str, dict[str, float]] = field(default_factory=dict)
    group_sigmas: dict[str, dict[str, float]] = field(default_factory=dict)
    shared_units: dict[str, str] = field(default_factory=dict)
    sharing_chi2: float = 0.0
    sharing_dof: int = 0


@dataclass
class Composition:
    """What the nonlinearity of a composed fit of linear effects acts on beside d_nom, per
    detector k: the signal x_k(t) = irfft(c_k . B_k) - o_k, with B_k the detector's
    template bank, c_k the fitted coefficients of its rows (0 for the nonlinearity's own
    rows, half a readout gain's: ``backfit.fit_iterative``) and o_k the offset taken out.
    Kept (a few numbers per detector) so that a candidate added to the fit can be
    screened with the nonlinearity's templates held there (:mod:`.frozen`)."""

    coefficients: list[np.ndarray]  # per detector, one per row of the whole bank
    offsets: np.ndarray  # o_k


@dataclass
class FitResult:
    """The fit of one set of effects."""

    selected: tuple[str, ...]
    chi2: float
    chi2_per_detector: np.ndarray
    n_params: int
    effects: dict[str, EffectFit]
    model_f: list[np.ndarray] | None = field(repr=False)  # rfft of the masked model per detector
    parts: dict | None = field(default=None, repr=False)  # effect -> per-detector rfft model

    prior_penalty: float = 0.0  # sum of the selected effects' Effect.prior_penalty
    # with the nonlinearity composed with other signal effects: its first fit's variance
    # inflation per detector (how much of g1 the others could take at first order), and
    # the fits from the other starts (backfit.fit_composed) when they ran
    first_pass_inflation: np.ndarray | None = field(default=None, repr=False)
    alternatives: list[FitResult] = field(default_factory=list, repr=False)
    # with the nonlinearity composed: a relative gain drift fitted after it (a readout gain)
    gain_after: bool = False
    # the nonlinearity composed on linear effects: the signal it acts on (a screen holds it)
    composition: Composition | None = field(default=None, repr=False)
    # a candidate's screen, not a fit of the set (:func:`.frozen.frozen_screen`)
    screened: bool = False

    def bic(self, ln_n_eff: float) -> float:
        return self.chi2 + self.n_params * ln_n_eff + self.prior_penalty
