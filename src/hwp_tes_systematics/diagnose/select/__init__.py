"""Joint fit of catalog effects to the residual, and forward stepwise selection with the BIC.

Modules: :mod:`.bank` (the template bank and its normal equations, the linear fit),
:mod:`.backfit` (nonlinear and event effects, fitted in turn), :mod:`.frozen` (the
screen of a step's candidates on a composed fit), :mod:`.stepwise`
(the stepwise selection), :mod:`.results` (what a fit gives), :mod:`.step` (the
pipeline's step).

Likelihood. Per detector k (detectors' noise independent), with R_f the rfft of the
masked residual r = valid x (recording - d_nom), M_f the rfft of the masked model of the
selected effects and S_f = P(f) n f_s v / 2 the expected periodogram of the noise
(:mod:`.noise`), the Whittle likelihood gives

    chi^2 = sum_k v_k sum_f 2 |R_f - M_f|^2 / S_f,

over the modes f != 0, f_Nyquist (the DC mode is left out: an offset is a nuisance),
v_k the detector's fraction of valid samples: a gap correlates the modes, n of them hold
n v independent ones (:func:`.noise.independent_fraction`), and for white noise this
chi^2 is the time-domain one over the valid samples.
With the noise weights S the ordinary chi^2 of the whitened Fourier coefficients, two real
degrees of freedom per mode (the noise is a nominal adjustment, fitted before the effects
and refitted on the residual of the best fit by :mod:`.pipeline`; the fit takes it as
given: ``with_noise``). N_eff = the number of real Fourier
degrees of freedom used (2 v_k per mode per detector) is the sample size of the

    BIC = chi^2 + k ln N_eff,

k the number of fitted parameters (per detector: each effect's parameters; per glitch:
amplitude, time and tail).

Fitting a set of effects. Each effect says how it is fitted by its ``kind``: "linear"
(templates), "nonlinear" (one parameter with a model of its own: the time constant),
"events" (a detector and a per-event fit: glitches); the fit names no effect.
Linear effects (templates T_j, :mod:`.effects`): weighted
linear least squares in the whitened Fourier domain, a = G^-1 b with
G_ij = sum_f 2 Re(T_i* T_j) / S_f, b_i = sum_f 2 Re(T_i* R_f) / S_f (columns scaled to
unit diagonal, pseudo-inverse of the normalised G, eigenvalues below 1e-12 dropped);
covariance G^-1. A nonlinear effect (the detector time constant tau):
``scipy.optimize.least_squares`` on the whitened residual with the linear parameters
profiled out (variable projection), started from the linearised solution (its
``linearised_f``: for tau the template -d d_nom/dt); covariance of (tau, a) from the
Jacobian, F = J^T J. Events (glitches): detected in the whitened residual of the other
effects by a robust (MAD) threshold and fitted per event (:mod:`.effects.glitches`);
an event is kept if its own Delta chi^2 = (A/sigma_A)^2 exceeds its BIC penalty 3 ln N_eff.
The nonlinearity acts on the total signal: its templates (d^2, and d^3 for the cubic
term) are recomputed on d = d_nom + (the fitted model of the other signal effects and of
the nominal adjustments refitted beside it) (the full forward model to second order, e.g.
a gain drift modulating the 4f line; and the pre-nonlinearity model: d_nom was adjusted
to a recording that holds the nonlinearity's own DC and 2f terms, which the refitted
adjustments take out), unless that cross term is below Delta chi^2 = 0.01; in
later passes they are rebuilt only when the fitted model moved enough since the last
build for the same term, 2 g1 d_nom (change of the model), to reach Delta chi^2 = 0.01
(a one-day pair: 125 -> 99 s, the same selection and chi^2); a rebuild that raises chi^2
by more than 1 above the lowest pass returns to it, and where the first fit shares a line
between the nonlinearity and another signal effect the fit is started three ways and
keeps the lowest chi^2, the others as its ``alternatives`` (:func:`.backfit.fit_composed`).
With nonlinear pieces, the
pieces are fitted in turn (backfitting, up to four passes, until chi^2 changes by less
than 0.05). Speed-up: the nonlinear fit is skipped when even
its linearised template, fitted beside the linear effects, gains less than half of its
BIC penalty plus |threshold| (a large tau, where the linearisation fails, gains a lot).
Likewise a forward step's candidate added to a composed fit of linear effects (a linear
effect, or the time constant by its first-order template) is first fitted once with the
nonlinearity's templates held where the current fit composed them
(:func:`.frozen.frozen_screen`); if it gains less than half its BIC penalty so, it cannot
pass and its composed fit is skipped: its entry in the step's table is that screen's
(``screened``). A swap step's trial (an unselected effect in a selected one's place) is
screened so too and left out where its held Delta BIC exceeds half the newcomer's
penalty; the final swap margins are full fits. Every fit the selection keeps is the
composed one, so the selection and its parameters are those of the full fits, bit for bit
(``tests/diagnose/test_frozen_screen.py``).

Selection (:func:`stepwise`). Start from the nominal model (no effect); at each step fit
every remaining effect jointly with the selected ones and compute
Delta BIC = BIC(selected + effect) - BIC(selected); keep the effect with the lowest
Delta BIC (equivalently the largest Delta chi^2 - Delta k ln N_eff) if it is below
``delta_bic_threshold`` (default -10: "very strong" evidence on the Kass & Raftery scale,
a Bayes factor above e^5 ~ 150) and stop otherwise. The lowest Delta BIC is used rather
than the largest Delta chi^2 because an effect with many parameters (hwpss_slow_modulation:
up to 24 per detector) gains Delta chi^2 from the noise alone; for the same reason the
HWPSS harmonics are tried line by line (two parameters per detector each, reported
together), and ``max_effects`` counts families, not lines. After each addition, a backward
step removes an effect that the later ones made redundant (its removal raises the BIC by
less than |threshold|); a set once removed is not revisited, so the search ends. Last, a
selected linear signal effect is swapped for an unselected one when that lowers the BIC
(forward selection never revisits its first choice, made with the noise weights of that
moment: an HWP temperature drift taken before the refitted 1/f noise lets a gain drift's
dipole drift show).

Uncertainties: linear parameters from G^-1 (inverse Fisher matrix of the whitened
Fourier fit, which includes the 1/f noise correlations); tau with the linear parameters
from the Jacobian; glitches from the local fit's Jacobian (white noise).
"""

from .bank import DELTA_BIC_THRESHOLD, GAP_OFFSET, GLITCH_THRESHOLD_SIGMA, FitProblem
from .results import EffectFit, FitResult
from .step import Selection, select_effects
from .stepwise import Step, StepwiseResult, select_templates, stepwise

__all__ = [
    "DELTA_BIC_THRESHOLD",
    "GAP_OFFSET",
    "GLITCH_THRESHOLD_SIGMA",
    "EffectFit",
    "FitProblem",
    "FitResult",
    "Selection",
    "Step",
    "StepwiseResult",
    "select_effects",
    "select_templates",
    "stepwise",
]
