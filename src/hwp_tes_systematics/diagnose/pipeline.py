"""``diagnose``: the pipeline, as named steps, each a function of the previous steps' outputs.

    1 nominal fit    d_nom = sky + dipole + A_2 cos 2(chi - theta) (:mod:`.model`) and its
                     adjustments: gain, offset, 2f amplitude/phase, polarisation angle, sky
                     scales, noise (fitted, never effects): NominalFit,
                     r = recording - adjusted d_nom     (:mod:`.nominal`)
    2 locate         where r differs from noise: lines, HWP-angle harmonics, transients,
                     drifts, sky: Mismatch              (:mod:`.locate`)
    3 select         which effects explain r: stepwise by the BIC over the catalog, jointly
                     with the adjustments; noise refitted, selection checked again:
                     Selection                          (:mod:`.select`)
    4 explain        each effect's parameters, evidence and look-alikes; what is left,
                     structure no effect explains       (:mod:`.explain`)
    5 bound          g1 against the requirement         (:mod:`.bound`)
    6 report         the Diagnosis, and its files       (:mod:`.report`)

Returns the ``diagnosis.json``-shaped dict::

    {"mismatch_found": bool,            # an effect, or unexplained structure
     "effects": [{"name", "title", "parameters": {"g1[det]": {"value", "sigma", "unit", ...}},
                  "delta_chi2", "delta_bic", "evidence", ...}, ...],   # ranked
     "unexplained": [{"kind", "freq_hz" | "time_range_s" | ..., "significance_sigma",
                      "tried_and_rejected", "text"}, ...],
     "nominal_adjustments": {detector: {name: {"value", "sigma", "unit", "nominal"}}},
     "chi2_before", "chi2_after", "dof", "n_eff", "delta_bic_threshold",
     "steps": [...], "swap_margins": {"effects": {effect: {look-alike: Delta BIC}}},
     "lines": [...], "noise": {...}, "locate": {...}, "recording": {...}}

"effects" is ranked by the drop-one Delta chi^2 (how much worse the final model gets
without the effect); "delta_bic" is BIC(final) - BIC(final without it) (< 0 for a
selected effect). With ``out_dir``, writes diagnosis.json, diagnosis.md and the figures
(:mod:`.report`).
"""

from __future__ import annotations

import logging
import time

from .bound import bound_g1
from .bound.requirement_check import load_requirement
from .explain import explain_effects, find_unexplained, left_at_its_signature
from .locate import locate
from .nominal import fit_nominal_model
from .nominal.adjustments import SKY_RESIDUAL_NSIDE
from .recording import Recording
from .report import Diagnosis, ReportPaths, report, write_outputs
from .select import select_effects

log = logging.getLogger(__name__)


class _Progress:
    """The pipeline's stages on the log (INFO; the command line shows them on stderr):
    '<source>: [12.3 s] stage ...', the time since the diagnosis started."""

    def __init__(self, source: str):
        self.source, self.start = source, time.monotonic()

    def __call__(self, message: str, *args) -> None:
        log.info("%s: [%.1f s] " + message, self.source, time.monotonic() - self.start, *args)


def diagnose(
    recording: Recording,
    sky_iqu,
    a2_k,
    nominal_noise=None,
    out_dir=None,
    delta_bic_threshold: float = -10.0,
    max_effects: int = 6,
    workers: int = 1,
    figures: bool = True,
    sky_residual_nside: int | None = SKY_RESIDUAL_NSIDE,
    requirement=None,
) -> Diagnosis:
    """Diagnose ``recording`` against its simulation (module docstring); never told the effect.

    ``sky_iqu``: (3, npix) I, Q, U map [K_CMB, Galactic, RING] or the path of a FITS map;
    ``a2_k``: the nominal HWPSS amplitude A_2 [K] (scalar or one per detector);
    ``nominal_noise``: the configured noise (see :func:`.nominal.step._nominal_noise_models`; default:
    the recording's detector metadata); ``delta_bic_threshold``: an effect is kept if it
    lowers the BIC by more than this (default -10); ``requirement``: the ``requirement.json``
    of a workflow run a found nonlinearity is compared with (default: the shipped one-year
    result; :mod:`.bound.requirement_check`). Returns the :class:`.report.diagnosis.Diagnosis`
    (what ``diagnosis.json`` holds); with ``out_dir`` (a folder, or the exact paths as a
    :class:`.report.diagnosis.ReportPaths`) the report is also written there.
    The steps: :func:`.nominal.step.fit_nominal_model`, :func:`.locate.step.locate`,
    :func:`.select.step.select_effects`, :func:`.explain.step.explain_effects`,
    :func:`.bound.step.bound_g1`, :func:`.explain.unexplained.find_unexplained`,
    :func:`.report.step.report`.
    """
    if not isinstance(recording, Recording):
        raise TypeError(f"recording: expected a Recording, got {type(recording).__name__}")
    # a requirement file given is read first: a bad one stops before the long diagnosis
    requirement_given = None if requirement is None else load_requirement(requirement)
    progress = _Progress(recording.source)
    progress(
        "nominal model (%d detectors x %d samples, %.2f h)",
        recording.n_detectors,
        recording.n_samples,
        recording.duration_s / 3600,
    )
    progress("fitting the nominal adjustments")
    fit = fit_nominal_model(
        recording,
        sky_iqu,
        a2_k,
        nominal_noise,
        sky_residual_nside,
        delta_bic_threshold,
        workers,
    )
    progress("locating where the residual differs from noise")
    mismatch = locate(
        fit.context,
        fit.residual,
        fit.noise_models,
        fit.nominal,
        workers=workers,
        residual_f=fit.residual_f,
    )
    selection = select_effects(fit, delta_bic_threshold, max_effects, workers, progress)
    effects = explain_effects(fit, selection, delta_bic_threshold, workers)
    requirement_check = bound_g1(effects, selection, requirement_given or load_requirement())
    progress("looking for unexplained structure")
    unexplained = find_unexplained(
        fit.context, selection.residual_after, selection.noise_models, selection.history, workers
    )
    for entry in effects:
        left_at_its_signature(entry, unexplained)
    result = report(
        fit, selection, mismatch, effects, unexplained, requirement_check, delta_bic_threshold
    )
    if out_dir is not None:
        progress("writing the report and figures: %s", ReportPaths.of(out_dir).markdown)
        write_outputs(
            result,
            out_dir,
            fit.context,
            selection.problem,
            fit.residual,
            selection.residual_after,
            mismatch,
            selection.noise_models,
            figures=figures,
        )
    progress("done: %s", ", ".join(e["name"] for e in effects) or "no effect selected")
    return result
