"""Step 4 of the diagnosis: each selected effect as the report gives it, with its evidence and
look-alikes."""

from __future__ import annotations

import numpy as np

from ..effects import CATALOG, family_of, noise_effect, prior_penalty_of, reported_name
from ..nominal.adjustments import NOMINAL
from ..nominal.step import NominalFit
from ..select.step import Selection
from .evidence import Evidence


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
    corrections = final.effects[NOMINAL.name].values  # the 2f amplitude before any event
    a2_before_k = np.hypot(ctx.a2_k + corrections["a2_cos"], corrections["a2_sin"])
    for name in steps.ranked:
        fitted = CATALOG[name].before_events(final.effects[name], ctx, a2_before_k)
        evidence = Evidence(ctx, selection.partial[name], noise_models, ctx.a2_k, workers)
        text = CATALOG[name].evidence(evidence, fitted) + _gain_order(final, name)
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
                "scope": effect.scope(ctx, fitted),
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
    crosstalk = selection.crosstalk
    if crosstalk is not None and crosstalk.common is not None:  # a noise common to groups
        common = CATALOG["common_mode_noise"]
        effects_out.append(common.noise_entry(ctx, crosstalk, noise_models))
    if crosstalk is not None and crosstalk.delta_bic < delta_bic_threshold:
        effects_out.append(noise_effect("correlation").noise_entry(ctx, crosstalk, noise_models))
    return merge_members(effects_out)


def look_alikes(steps, threshold: float) -> dict[str, list[str]]:
    """For each effect added: the candidates whose Delta BIC, their prior penalties left
    out, came within |threshold| of it.

    Those explained the residual (nearly) equally well at that step, so the data do not
    tell them apart (e.g. a gain drift and a 2f amplitude drift in a recording too short
    for the dipole's change to show): the report says so instead of picking silently.
    An effect that replaced another (one family explaining the lines as well, see
    :func:`.select.select_templates`) names the one it replaced.
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
        # the data's part of the BIC: a prior penalty (Effect.prior_penalty) is not the
        # data telling two effects apart, so it is left out of the comparison
        best = step.candidates[step.added]["delta_bic"] - prior_penalty_of(step.added)
        ties = [
            name
            for name, c in step.candidates.items()
            if not same_physics(name, step.added)
            and c["delta_bic"] - prior_penalty_of(name) - best < -threshold
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


def left_at_its_signature(entry: dict, unexplained: list[dict]) -> None:
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


def _gain_order(final, name: str) -> str:
    """Which side of the nonlinearity a relative gain drift acts on, where the composed fit
    tried both (:func:`..select.backfit.fit_composed`); '' otherwise."""
    if CATALOG[name].stage != "response":
        return ""
    other = next((alt for alt in final.alternatives if alt.gain_after != final.gain_after), None)
    if other is None:
        return ""
    where = (
        "after it, as a readout gain: (1 + delta)(d + g1 d^2)"
        if final.gain_after
        else "before it, as an optical or TES gain: D + g1 D^2 with D = (1 + delta) d"
    )
    return (
        f"; the gain drift acts {where} (chi^2 lower by {other.chi2 - final.chi2:.3g} than "
        "with the other order)"
    )
