"""``diagnose``: the pipeline, as named steps, each a function of the previous steps' outputs.

    1 nominal fit    d_nom = sky + dipole + A_2 cos 2(chi - theta) (:mod:`.model`) and its
                     adjustments: gain, offset, 2f amplitude/phase, polarisation angle, sky
                     scales, noise (fitted, never effects; :mod:`.nominal`): NominalFit,
                     r = recording - adjusted d_nom     (:func:`fit_nominal_model`)
    2 locate         where r differs from noise: lines, HWP-angle harmonics, transients,
                     drifts, sky (:func:`.locate.locate`)
    3 select         which effects explain r: stepwise by the BIC over the catalog, jointly
                     with the adjustments; noise refitted, selection checked again
                     (:mod:`.fit`): Selection      (:func:`select_effects`)
    4 explain        each effect's parameters, evidence and look-alikes (:func:`explain_effects`);
                     what is left, structure no effect explains (:mod:`.unexplained`)
    5 bound          g1 against the requirement (:func:`bound_g1`)
    6 report         the Diagnosis (:func:`report`); written by :func:`.report.write_outputs`

Returns the ``diagnosis.json``-shaped dict::

    {"mismatch_found": bool,            # an effect, or unexplained structure
     "effects": [{"name", "title", "parameters": {"g1[det]": {"value", "sigma", "unit", ...}},
                  "delta_chi2", "delta_bic", "evidence", ...}, ...],   # ranked
     "unexplained": [{"kind", "freq_hz" | "time_range_s" | ..., "significance_sigma",
                      "tried_and_rejected", "text"}, ...],
     "nominal_adjustments": {detector: {name: {"value", "sigma", "unit", "nominal"}}},
     "chi2_before", "chi2_after", "dof", "n_eff", "delta_bic_threshold",
     "steps": [...], "lines": [...], "noise": {...}, "locate": {...}, "recording": {...}}

"effects" is ranked by the drop-one Delta chi^2 (how much worse the final model gets
without the effect); "delta_bic" is BIC(final) - BIC(final without it) (< 0 for a
selected effect). With ``out_dir``, writes diagnosis.json, diagnosis.md and the figures
(:mod:`.report`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np
import scipy.fft

from .effects import CATALOG, Effect, family_of, reported_name
from .evidence import Evidence
from .fit import FitProblem, stepwise
from .locate import line_at, locate
from .model import build_context, load_sky, nominal_tod, per_detector
from .noise import NoiseModel, estimate_noise, fitted_modes
from .nominal import (
    NOMINAL,
    SKY_RESIDUAL_NSIDE,
    adjustments_report,
    fit_nominal,
    refit_noise,
)
from .recording import Recording
from .report import Diagnosis, ReportPaths, write_outputs
from .requirement_check import (
    NONLINEARITY_FAMILY,
    bound_nonlinearity,
    compare_nonlinearity,
    load_requirement,
)
from .unexplained import find_unexplained

log = logging.getLogger(__name__)


class _Progress:
    """The pipeline's stages on the log (INFO; the command line shows them on stderr):
    '<source>: [12.3 s] stage ...', the time since the diagnosis started."""

    def __init__(self, source: str):
        self.source, self.start = source, time.monotonic()

    def __call__(self, message: str, *args) -> None:
        log.info("%s: [%.1f s] " + message, self.source, time.monotonic() - self.start, *args)


NOISE_REFIT_CHANGE = 0.02  # select again when the noise PSD at the effects moved by > 2 %

__all__ = [
    "bound_g1",
    "diagnose",
    "explain_effects",
    "fit_nominal_model",
    "nominal_tod",
    "report",
    "select_effects",
]


def _nominal_noise_models(recording: Recording, nominal_noise) -> list[NoiseModel]:
    """Noise per detector: from ``nominal_noise`` or the recording's detector metadata.

    ``nominal_noise``: None, (net_ukrts, fknee_mhz, alpha[, fmin_hz]), a dict with those
    keys, a NoiseModel, or a list of one of these per detector.
    """
    n_det = recording.n_detectors
    metadata = recording.nominal_noise()
    if nominal_noise is None:
        items = [None] * n_det
    elif (
        isinstance(nominal_noise, list)
        and len(nominal_noise) == n_det
        and not all(isinstance(x, (int, float)) for x in nominal_noise)
    ):
        items = list(nominal_noise)
    else:
        items = [nominal_noise] * n_det
    models = []
    for k, item in enumerate(items):
        meta = metadata[k]
        if item is None:
            values = meta
        elif isinstance(item, NoiseModel):
            models.append(item)
            continue
        elif isinstance(item, dict):
            values = {**meta, **item}
        else:
            item = tuple(item)
            if len(item) not in (3, 4):
                raise ValueError(
                    f"nominal_noise = {nominal_noise!r}: expected (net_ukrts, fknee_mhz, alpha"
                    "[, fmin_hz])"
                )
            values = dict(meta)
            values.update(zip(("net_ukrts", "fknee_mhz", "alpha", "fmin_hz"), item, strict=False))
        if not (math.isfinite(values["net_ukrts"]) and values["net_ukrts"] > 0):
            # no NET in the file (a lab detector): the noise is a nominal adjustment
            # anyway; it starts from a robust estimate on the residual (see diagnose)
            log.warning(
                "%s: no NET for detector %r in the file: the noise starts from the residual",
                recording.source,
                recording.detector_names[k],
            )
            models.append(None)
            continue
        models.append(NoiseModel.from_detector(values))
    return models


def _left_at_its_signature(entry: dict, unexplained: list[dict]) -> None:
    """An effect whose own lines (``Effect.signature_lines``) are left in ``unexplained``
    describes them only in part, e.g. the 4f leakage taking the part of an HWP wobble's
    4 f_HWP +- f_spin lines that follows the dipole: said in its evidence, ``partial``."""
    effect = CATALOG.get(entry["name"])
    own = set(getattr(effect, "signature_lines", ()))
    left = sorted(
        {
            u["identification"]
            for u in unexplained
            if u.get("kind") == "line" and (u.get("n_hwp"), u.get("m_spin")) in own
        }
    )
    entry["partial"] = bool(left)
    if left:
        entry["evidence"] += (
            f"; lines of its own signature are left unexplained ({', '.join(left)}): it "
            "describes them only in part, so something outside the catalog may share them "
            "(see What the fit cannot explain)"
        )


def _nonlinearity_bound(problem: FitProblem, final, requirement: dict) -> dict:
    """No nonlinearity selected: g1 fitted beside the final selection (the selection's last
    step tried it, so the fit is cached) bounds it (:func:`.requirement_check.bound_nonlinearity`)."""
    name = NONLINEARITY_FAMILY
    beside = problem.fit((*final.selected, name))
    effect = CATALOG[name]
    parameters = effect.reported_parameters(
        beside.effects[name],
        problem.ctx.detector_names,
        problem.ctx.sampling_rate_hz,
        problem.units[name],
    )
    return bound_nonlinearity(parameters, requirement, beside.chi2 - final.chi2)


def look_alikes(steps, threshold: float) -> dict[str, list[str]]:
    """For each effect added: the candidates whose Delta BIC came within |threshold| of it.

    Those explained the residual (nearly) equally well at that step, so the data do not
    tell them apart (e.g. a gain drift and a 2f amplitude drift in a recording too short
    for the dipole's change to show): the report says so instead of picking silently.
    An effect that replaced another (one family explaining the lines as well, see
    :func:`.fit.select_templates`) names the one it replaced.
    A nested variant of the same physics (``Effect.extends``) is not a look-alike.
    """

    def same_physics(a: str, b: str) -> bool:
        return family_of(a) == family_of(b)

    out: dict[str, list[str]] = {}
    for step in steps:
        if step.added and step.removed:  # a replacement: named if (nearly) as good
            if step.delta_bic > threshold:
                out[step.added] = sorted(set(out.get(step.added, [])) | {step.removed})
            continue
        if not step.added or step.added not in step.candidates:
            continue
        best = step.candidates[step.added]["delta_bic"]
        ties = [
            name
            for name, c in step.candidates.items()
            if not same_physics(name, step.added) and c["delta_bic"] - best < -threshold
        ]
        out[step.added] = sorted(set(out.get(step.added, [])) | set(ties))
    return out


def merge_members(effects: list[dict]) -> list[dict]:
    """The report's entries with the members of one family (``Effect.reported_as``: the
    lines of hwpss_harmonics) merged into one entry under the family's name: parameters
    and evidence joined, Delta chi^2 and Delta BIC summed, look-alikes named by what the
    report calls them; ranked again by Delta chi^2."""
    merged: dict[str, dict] = {}
    for entry in effects:
        effect = CATALOG[entry["name"]]
        name = reported_name(entry["name"])
        look_alikes = {reported_name(n) for n in entry["look_alikes"]}
        if name not in merged:
            family = CATALOG[name]
            merged[name] = dict(
                entry,
                name=name,
                title=family.title,
                signature=family.signature,
                look_alikes=sorted(look_alikes - {name}),
            )
            if effect.reported_as:
                merged[name]["members"] = [entry["name"]]
                merged[name]["main_parameters"] = list(entry["main_parameters"])
            continue
        into = merged[name]
        into["members"].append(entry["name"])
        into["main_parameters"] += entry["main_parameters"]
        into["parameters"] = {**into["parameters"], **entry["parameters"]}
        into["delta_chi2"] += entry["delta_chi2"]
        into["delta_bic"] += entry["delta_bic"]
        into["evidence"] += "; " + entry["evidence"]
        into["look_alikes"] = sorted((set(into["look_alikes"]) | look_alikes) - {name})
    return sorted(merged.values(), key=lambda e: -e["delta_chi2"])


def _line_table(mismatch, ctx, residual_before, residual_after, noise_models):
    rows = []
    for line in mismatch.lines:
        k = ctx.detector_names.index(line.detector)
        psd = float(noise_models[k].psd(line.freq_hz))
        after = line_at(residual_after[k], ctx.times_s, ctx.valid[k], line.freq_hz, psd)
        rows.append(
            {
                "detector": line.detector,
                "freq_hz": line.freq_hz,
                "identification": line.identification,
                "amplitude_before_k": line.amplitude_k,
                "sigma_k": line.sigma_amplitude_k,
                "significance_before_sigma": line.significance_sigma,
                "global_significance_sigma": line.global_sigma,
                "modulation_before_k": line.modulation_k,
                "modulation_significance_sigma": line.modulation_sigma,
                "amplitude_after_k": after[0],
                "significance_after_sigma": after[3],
            }
        )
    return rows


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


@dataclasses.dataclass
class NominalFit:
    """Step 1 (:func:`fit_nominal_model`): the recording against its adjusted simulation."""

    recording: Recording
    sky_source: str  # where the sky came from (a path, or "array")
    a2_k: np.ndarray  # (n_det,) nominal A_2 [K]
    nominal: list[NoiseModel]  # the configured noise, or the recording's estimate
    estimates: list  # the noise estimated on the first residual (noise.NoiseEstimate)
    adjusted: object  # nominal.fit_nominal's result (its noise follows the later steps)
    noise_models: list  # the noise the fit weighs with (a pole added if it rolls off)
    residual: np.ndarray  # (n_det, n_samples) recording - adjusted d_nom [K], 0 where invalid
    residual_f: np.ndarray  # its real FFT

    @property
    def context(self):
        """The adjusted model's :class:`.model.Context`."""
        return self.adjusted.context


@dataclasses.dataclass
class Selection:
    """Step 3 (:func:`select_effects`): the effects the BIC keeps, fitted jointly."""

    problem: FitProblem  # the template bank and normal equations of the last pass
    steps: object  # fit.stepwise's result of the last pass (ranked, delta_chi2, ...)
    final: object  # the joint fit of the selected effects
    history: list  # every step of every pass
    fluctuation: object  # the fitted excess noise (noise_effect("excess").fit_noise) or None
    rolloff: object  # the noise's roll-off beside the effects (noise_effect("rolloff").fit_noise)
    noise_models: list  # the noise of the final fit
    residual_after: np.ndarray  # (n_det, n_samples) the residual less the final fit [K]
    partial: dict  # {effect: the residual with that effect alone put back}


def fit_nominal_model(
    recording: Recording,
    sky_iqu,
    a2_k,
    nominal_noise,
    sky_residual_nside,
    delta_bic_threshold: float,
    workers: int,
) -> NominalFit:
    """Step 1: d_nom of the recording, the noise estimated on its residual where none is
    configured, the nominal adjustments fitted (gain, 2f amplitude and phase, polarisation
    angle, sky scales, offsets, sky residual, noise: never effects), and the noise's
    roll-off (:mod:`.rolloff`) taken into the noise model if it lowers the BIC by more than
    ``delta_bic_threshold`` (white + 1/f alone would pass it for a ~1 Hz knee)."""
    sky, sky_source = load_sky(sky_iqu)
    a2 = per_detector(a2_k, recording.n_detectors, "a2_k")
    nominal = _nominal_noise_models(recording, nominal_noise)
    base = build_context(recording, sky, a2)
    residual0 = np.where(base.valid, recording.tod - base.d_nom, 0.0)
    estimates = [
        estimate_noise(
            residual0[k],
            base.sampling_rate_hz,
            base.valid[k],
            base.f_hwp_hz,
            base.f_spin_hz,
            nominal[k].fmin_hz if nominal[k] is not None else 1e-5,
            start=nominal[k],
        )
        for k in range(base.n_detectors)
    ]
    nominal = [m if m is not None else e.model for m, e in zip(nominal, estimates, strict=True)]
    adjusted = fit_nominal(
        base,
        recording.tod,
        nominal,
        sky_residual_nside=sky_residual_nside,
        workers=workers,
    )
    ctx = adjusted.context
    noise_models = adjusted.noise
    residual = np.where(ctx.valid, recording.tod - ctx.d_nom, 0.0)
    modes = fitted_modes(residual.shape[1])
    residual_f = scipy.fft.rfft(residual, axis=-1, workers=workers)  # locate's and FitProblem's too
    ln_n_eff = math.log(2 * modes.sum() * ctx.n_detectors)
    # fitted before any effect, on the residual without the HWP lines: a strong line (the
    # 4f of a nonlinearity, 21 mK on H3-402 at g1 = 3e-3) cut by a gap leaks over the whole
    # band and passed for a pole of 27 ms, which corrupted every later noise fit
    line_free_f = residual_f - scipy.fft.rfft(adjusted.nuisance_lines_tod, axis=-1, workers=workers)
    early = noise_effect("rolloff").fit_noise(ctx, line_free_f, noise_models, modes, ln_n_eff)
    if early.delta_bic < delta_bic_threshold and not _sidebands_fit_better(
        ctx, early, line_free_f, noise_models, modes, ln_n_eff
    ):
        noise_models = adjusted.noise = early.noise
    return NominalFit(
        recording, sky_source, a2, nominal, estimates, adjusted, noise_models, residual, residual_f
    )


def select_effects(
    fit: NominalFit, delta_bic_threshold: float, max_effects: int, workers: int, progress
) -> Selection:
    """Step 3: the catalog's effects selected stepwise by the BIC, jointly with the
    adjustments (:func:`.fit.stepwise`). The noise was fitted before any effect was
    removed, and a strong effect leaks power beyond its line bins: it is refitted on the
    residual of the best fit and, if it moved by more than NOISE_REFIT_CHANGE where the
    effects are, or a gain fluctuation (:mod:`.fluctuations`, an excess noise in the 2f
    sidebands) is taken into it, the selection runs again with the new weights, starting
    from the effects found. Then the fluctuation and the noise's roll-off are fitted
    again beside the final effects. Updates ``fit.adjusted.noise``."""
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
    for attempt in range(2):
        if attempt:  # same templates and residual, new noise weights
            problem = problem.with_noise(noise_models)
        progress(
            "selecting effects (pass %d%s)", attempt + 1, ", noise refitted" if attempt else ""
        )
        steps = stepwise(
            problem,
            delta_bic_threshold=delta_bic_threshold,
            max_effects=max_effects,
            initial=previous,
        )
        final = problem.fit(steps.final.selected, keep_model=True)
        history += steps.steps
        log.debug("selected: %s", ", ".join(final.selected) or "nothing")
        if attempt == 1:
            break
        remaining_f = problem.residual_f - np.array(final.model_f)
        fluctuation = noise_effect("excess").fit_noise(
            ctx, remaining_f, noise_models, problem.modes, problem.ln_n_eff, also_from=nominal
        )
        if fluctuation.delta_bic < delta_bic_threshold:
            noise_models = fluctuation.noise
            adjusted.noise = fluctuation.base_noise
            previous = final.selected  # checked again with the new weights, then extended
            continue
        fluctuation = None
        if not final.selected:
            break
        refit, covariances, change = refit_noise(ctx, remaining_f, noise_models)
        if change < NOISE_REFIT_CHANGE:
            break
        noise_models = refit
        adjusted.noise, adjusted.noise_covariance = refit, covariances
        previous = final.selected  # checked first with the new weights, then extended
    remaining_f = problem.residual_f - np.array(final.model_f)  # of the final fit

    def fluctuation_beside(noise):
        return noise_effect("excess").fit_noise(
            ctx, remaining_f, noise, problem.modes, problem.ln_n_eff, also_from=nominal
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
    return Selection(
        problem,
        steps,
        final,
        history,
        fluctuation,
        rolloff,
        noise_models,
        residual_after,
        partial,
    )


def explain_effects(
    fit: NominalFit, selection: Selection, delta_bic_threshold: float, workers: int
) -> list[dict]:
    """Step 4: each selected effect as the report gives it (ranked by its drop-one
    Delta chi^2): its parameters with errors, its evidence in words, the effects it is
    not told apart from in this recording (selected within the threshold of it, or whose
    telling signature is below detection); the gain fluctuation and the noise's roll-off
    where fitted; a family's members merged (:func:`merge_members`)."""
    ctx, final, steps = fit.context, selection.final, selection.steps
    noise_models, problem = selection.noise_models, selection.problem
    ties = {  # named as the report names them (a member by its family)
        name: sorted({reported_name(n) for n in others})
        for name, others in look_alikes(selection.history, delta_bic_threshold).items()
    }
    found = {family_of(n) for n in steps.ranked}
    effects_out = []
    for name in steps.ranked:
        fitted = final.effects[name]
        evidence = Evidence(ctx, selection.partial[name], noise_models, ctx.a2_k, workers)
        text = CATALOG[name].evidence(evidence, fitted)
        if ties.get(name):
            text += (
                f"; NOT told apart in this recording from {', '.join(ties[name])} (within "
                f"{-delta_bic_threshold:g} of it in BIC when it was selected, or in chi^2 when "
                "it replaced it): the data fit either equally well, so read it as one of these"
            )
        unresolved = [
            other
            for other in CATALOG[name].unresolved_look_alikes(evidence, fitted)
            if other not in ties.get(name, []) and other not in found
        ]
        if unresolved:
            text += (
                f"; NOT told apart from {', '.join(unresolved)}: the signature that would "
                "tell them apart is below detection in this recording"
            )
            ties[name] = sorted(set(ties.get(name, [])) | set(unresolved))
        effect = CATALOG[name]
        effects_out.append(
            {
                "name": name,
                "title": effect.title,
                "parameters": effect.reported_parameters(
                    fitted, ctx.detector_names, ctx.sampling_rate_hz, problem.units[name]
                ),
                "main_parameters": list(effect.main_parameters),
                "delta_chi2": steps.delta_chi2[name],
                "delta_bic": steps.delta_bic[name],
                "evidence": text,
                "signature": effect.signature,
                "look_alikes": ties.get(name, []),
            }
        )
    if selection.fluctuation is not None:
        excess = noise_effect("excess")
        effects_out.append(excess.noise_entry(ctx, selection.fluctuation, noise_models))
    rolloff = selection.rolloff
    if rolloff.delta_bic < delta_bic_threshold:
        pole = noise_effect("rolloff")
        entry = next((e for e in effects_out if e["name"] == pole.name), None)
        new = pole.noise_entry(ctx, rolloff, noise_models)
        if entry is None:
            effects_out.append(new)
        else:  # also seen in the lines: the noise's roll-off added to its evidence
            entry["evidence"] += "; " + new["evidence"]
    return merge_members(effects_out)


def bound_g1(effects: list[dict], selection: Selection, requirement: dict) -> dict:
    """Step 5: the nonlinearity against the requirement of a workflow run: the fitted g1
    if the nonlinearity was selected, else what the recording says of g1 all the same
    (its fit beside the effects found; :mod:`.requirement_check`)."""
    nonlinearity = next((e for e in effects if family_of(e["name"]) == NONLINEARITY_FAMILY), None)
    if nonlinearity is not None:
        return {"effect": nonlinearity["name"], **compare_nonlinearity(nonlinearity, requirement)}
    bound = _nonlinearity_bound(selection.problem, selection.final, requirement)
    return {"effect": None, **bound}


def report(
    fit: NominalFit,
    selection: Selection,
    mismatch,
    effects: list[dict],
    unexplained: list[dict],
    requirement_check: dict,
    delta_bic_threshold: float,
) -> Diagnosis:
    """Step 6: the :class:`.report.Diagnosis` (what ``diagnosis.json`` holds; the module
    docstring) of the steps' outputs."""
    recording, ctx, adjusted = fit.recording, fit.context, fit.adjusted
    steps, final, noise_models = selection.steps, selection.final, selection.noise_models
    lines = _line_table(mismatch, ctx, fit.residual, selection.residual_after, noise_models)
    corrections = final.effects[NOMINAL.name]
    adjustments = adjustments_report(
        adjusted, corrections.values, corrections.sigmas, fit.nominal, recording.pol_angles_rad
    )
    n_nuisance = len(NOMINAL.parameters) * ctx.n_detectors + 3 * ctx.n_detectors + ctx.n_detectors
    n_nuisance += adjusted.sky_residual_pixels
    result = {
        "mismatch_found": bool(effects) or bool(unexplained),
        "effects": effects,
        "unexplained": unexplained,
        "nominal_adjustments": adjustments,
        "chi2_before": steps.baseline.chi2,
        "chi2_after": final.chi2,
        "dof": steps.n_eff - final.n_params - n_nuisance,
        "n_nuisance_parameters": n_nuisance,
        "n_eff": steps.n_eff,
        "n_params": final.n_params,
        "bic_before": steps.baseline.bic(steps.ln_n_eff),
        "bic_after": final.bic(steps.ln_n_eff),
        "delta_bic_threshold": delta_bic_threshold,
        "information_criterion": "BIC = chi2 + k ln N_eff (N_eff = real Fourier dof used)",
        "requirement_check": requirement_check,
        "steps": [dict(step.as_dict(), step=i + 1) for i, step in enumerate(selection.history)],
        "lines": lines,
        "noise": {
            "nominal": [
                {
                    "net_k_sqrt_s": m.net_k_sqrt_s,
                    "fknee_hz": m.fknee_hz,
                    "alpha": m.alpha,
                    "fmin_hz": m.fmin_hz,
                }
                for m in fit.nominal
            ],
            "estimated": [e.as_dict() for e in fit.estimates],
            # the noise the final fit weighs with (refitted beside the effects found and a
            # gain fluctuation's sidebands; "estimated" is the recording's before any fit)
            "final": [
                {
                    "net_k_sqrt_s": m.net_k_sqrt_s,
                    "fknee_hz": m.fknee_hz,
                    "alpha": m.alpha,
                    "tau_s": m.tau_s,
                }
                for m in (getattr(m, "base", m) for m in noise_models)
            ],
            "rolloff": selection.rolloff.as_dict(),
        },
        "locate": mismatch.as_dict(),
        "recording": {
            "source": recording.source,
            "channel": recording.channel,
            "detectors": ctx.detector_names,
            "duration_s": recording.duration_s,
            "sampling_rate_hz": recording.sampling_rate_hz,
            "start_time_mjd": float(recording.start_time.mjd),
            "start_time_scale": recording.start_time.scale,
            "flagged_fraction": float(np.mean(recording.flags)),
            "sky": fit.sky_source,
            "a2_k": fit.a2_k.tolist(),
            "f_hwp_hz": ctx.f_hwp_hz,
        },
    }
    return Diagnosis(_jsonable(result))


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
    ``nominal_noise``: the configured noise (see :func:`_nominal_noise_models`; default:
    the recording's detector metadata); ``delta_bic_threshold``: an effect is kept if it
    lowers the BIC by more than this (default -10); ``requirement``: the ``requirement.json``
    of a workflow run a found nonlinearity is compared with (default: the shipped one-year
    result; :mod:`.requirement_check`). Returns the :class:`.report.Diagnosis`
    (what ``diagnosis.json`` holds); with ``out_dir`` (a folder, or the exact paths as a
    :class:`.report.ReportPaths`) the report is also written there.
    The steps: :func:`fit_nominal_model`, :func:`.locate.locate`, :func:`select_effects`,
    :func:`explain_effects`, :func:`bound_g1`, :func:`.unexplained.find_unexplained`,
    :func:`report`.
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
        fit.context, selection.residual_after, selection.noise_models, selection.steps, workers
    )
    for entry in effects:
        _left_at_its_signature(entry, unexplained)
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


def _sidebands_fit_better(ctx, early, residual_f, noise_models, modes, ln_n_eff) -> bool:
    """Whether a gain fluctuation's 2f sidebands (:mod:`.fluctuations`) explain the residual
    better in BIC than the early roll-off does: their wings fall away from 2 f_HWP as a
    pole rolls the noise off, and a pole taken for them (up to its bound, ~46 ms, with the
    white level collapsing beneath) corrupts every later noise fit. The fluctuation itself
    is tested after the effects are fitted; here it only stops the pole."""
    sidebands = noise_effect("excess").fit_noise(ctx, residual_f, noise_models, modes, ln_n_eff)
    return sidebands.delta_bic < early.delta_bic


def noise_effect(signature: str) -> Effect:
    """The catalog's effect with this signature in the noise (``Effect.noise_signature``:
    "excess" or "rolloff"), fitted beside the selection."""
    found = [e for e in CATALOG.values() if e.noise_signature == signature]
    if len(found) != 1:
        names = [e.name for e in found]
        raise LookupError(
            f"one catalog effect with noise_signature {signature!r} expected: {names}"
        )
    return found[0]
