"""The diagnosis's result (:class:`Diagnosis`) and its report: ``diagnosis.json``,
``diagnosis.md`` (in words) and the figures.

The pipeline that computes the result is :mod:`.pipeline` (``diagnose``); this module
holds and writes what it found.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Iterator, Mapping
from pathlib import Path

from ...io import atomic_path
from ..effects import format_temperature

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class ReportPaths:
    """Where a diagnosis is written: ``json`` (diagnosis.json), ``markdown`` (diagnosis.md)
    and its figures, PNGs beside the Markdown that links them by name."""

    json: Path
    markdown: Path

    @classmethod
    def of(cls, where) -> ReportPaths:
        """``where`` as given (ReportPaths), or a folder: its diagnosis.json and .md."""
        if isinstance(where, ReportPaths):
            return where
        return cls(Path(where) / "diagnosis.json", Path(where) / "diagnosis.md")

    @property
    def figures_dir(self) -> Path:
        return self.markdown.parent


class Diagnosis(Mapping):
    """What :func:`.pipeline.diagnose` found in a recording, as ``diagnosis.json`` holds it.

    Read it as a mapping of the JSON's keys (``result["effects"]``, ``result["unexplained"]``,
    ``result["nominal_adjustments"]``, ...) or through the accessors below;
    :meth:`to_json` and :meth:`to_markdown` give the text of the two report files, and
    :meth:`read` reads a ``diagnosis.json`` back.
    """

    def __init__(self, data: Mapping):
        self._data = dict(data)

    def __getitem__(self, key: str):
        return self._data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __repr__(self) -> str:
        found = ", ".join(self.effect_names) or "no catalog effect"
        return (
            f"<Diagnosis of {self._data['recording']['source']}: {found}; "
            f"{len(self._data['unexplained'])} unexplained>"
        )

    @property
    def mismatch_found(self) -> bool:
        """True when an effect was selected or a structure is left unexplained."""
        return bool(self._data["mismatch_found"])

    @property
    def effect_names(self) -> list[str]:
        """The effects found, most important first (the report's names)."""
        return [effect["name"] for effect in self._data["effects"]]

    def effect(self, name: str) -> dict:
        """The report entry of the effect ``name`` (parameters, Delta chi^2, evidence, ...)."""
        for effect in self._data["effects"]:
            if effect["name"] == name:
                return effect
        raise KeyError(f"{name!r} was not found; the diagnosis found {self.effect_names}")

    def _detector(self, detector: int | str) -> str:
        names = self._data["recording"]["detectors"]
        return names[detector] if isinstance(detector, int) else detector

    def parameter(self, effect: str, name: str, detector: int | str) -> dict:
        """{value, sigma, unit, ...} of parameter ``name`` of ``effect`` for ``detector``
        (its index in the recording or its name)."""
        wanted = self._detector(detector)
        for entry in self.effect(effect)["parameters"].values():
            if entry["parameter"] == name and entry["detector"] == wanted:
                return entry
        raise KeyError(f"{effect}.{name} has no value for detector {wanted!r}")

    def adjustment(self, detector: int | str, name: str) -> dict:
        """{value, sigma, ...} of the nominal-model adjustment ``name`` of ``detector``."""
        return self._data["nominal_adjustments"][self._detector(detector)][name]

    @property
    def requirement_sentence(self) -> str | None:
        """The fitted nonlinearity against the requirement on sigma_g1, in one sentence (when
        none was found: the bound on g1 from its fit beside the effects found)."""
        check = self._data.get("requirement_check")
        return check["sentence"] if check else None

    def to_dict(self) -> dict:
        """The JSON content as a plain dict."""
        return dict(self._data)

    def to_json(self) -> str:
        """The text of ``diagnosis.json``."""
        return json.dumps(self._data, indent=2) + "\n"

    def to_markdown(self, figure_files: dict | None = None) -> str:
        """The text of ``diagnosis.md`` (:func:`markdown_report`)."""
        return markdown_report(self._data, figure_files)

    @classmethod
    def read(cls, path) -> Diagnosis:
        """A ``diagnosis.json`` read back."""
        return cls(json.loads(Path(path).read_text()))


def write_outputs(
    result, where, ctx, problem, residual, residual_after, mismatch, noise_models, figures=True
) -> None:
    """The report at ``where`` (:class:`ReportPaths`, or a folder for its default names):
    the JSON first, then the figures, then the Markdown. A figure that fails is logged
    and named in the Markdown; the JSON and the Markdown are written all the same."""
    paths = ReportPaths.of(where)
    for folder in {paths.json.parent, paths.figures_dir}:
        folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(paths.json) as temporary:
        temporary.write_text(Diagnosis(result).to_json())
    figure_files, figures_error = {}, None
    if figures:
        from .figures import diagnosis_figures

        try:
            figure_files = diagnosis_figures(
                paths.figures_dir, ctx, residual, residual_after, mismatch, noise_models, result
            )
        except Exception as error:  # the figures are a view: the report must not be lost
            log.exception("%s: the figures could not be drawn", paths.figures_dir)
            figures_error = f"{type(error).__name__}: {error}"
    with atomic_path(paths.markdown) as temporary:
        temporary.write_text(markdown_report(result, figure_files, figures_error))


def markdown_report(
    result: dict, figure_files: dict | None = None, figures_error: str | None = None
) -> str:
    """The human-readable report: what physics was left out, how sure, the evidence; its
    figures ({title: file name}), or why they could not be drawn."""
    rec = result["recording"]
    out = [
        "# Diagnosis of a recording against its simulation",
        "",
        (
            f"Recording: `{rec['source']}` ({rec['channel'] or 'no channel named'}, "
            f"detectors {', '.join(rec['detectors'])}, "
            f"{rec['duration_s'] / 3600:.3g} h at {rec['sampling_rate_hz']:g} Hz, "
            f"{100 * rec['flagged_fraction']:.2g} % flagged); A_2 = {rec['a2_k']} K; sky: {rec['sky']}."
        ),
        "",
    ]
    effects = result["effects"]
    unexplained = result.get("unexplained", [])
    if not result["mismatch_found"]:
        out += [
            (
                "**No mismatch found**: once the nominal model's adjustments are fitted (below), "
                "no effect of the catalog lowers the BIC by more than "
                f"{-result['delta_bic_threshold']:g} and no significant structure is left; the "
                f"residual is consistent with the fitted noise (chi2 = {result['chi2_before']:.1f} "
                f"for {result['dof']} degrees of freedom)."
            ),
            "",
        ]
    elif not effects:
        out += [
            (
                "**Mismatch found, but no catalog effect explains it**: see *What the fit "
                "cannot explain* below."
            ),
            "",
        ]
    else:
        out += [
            (
                f"**Mismatch found.** The simulation left out {len(effects)} effect(s); the fit "
                f"lowers chi2 from {result['chi2_before']:.1f} to {result['chi2_after']:.1f} "
                f"(N_eff = {result['n_eff']}, dof = {result['dof']}), BIC from "
                f"{result['bic_before']:.1f} to {result['bic_after']:.1f}."
            ),
            "",
        ]
    check = result.get("requirement_check")
    for rank, effect in enumerate(effects, 1):
        out += [
            f"## {rank}. {effect['title']} (`{effect['name']}`)",
            "",
            (
                f"*How sure*: removing it from the final model raises chi2 by "
                f"{effect['delta_chi2']:.4g} and the BIC by {-effect['delta_bic']:.4g} "
                f"(threshold {-result['delta_bic_threshold']:g})."
            ),
            "",
            f"*Signature*: {effect['signature']}.",
            "",
            f"*Evidence*: {effect['evidence']}.",
            "",
        ]
        out += scope_lines(effect, len(rec["detectors"]))
        out += parameter_table(effect["parameters"]) + [""]
        if check and check["effect"] == effect["name"]:
            out += [f"*Against the requirement*: {check['sentence']}", ""]
    if check and check["effect"] is None:  # no nonlinearity found: what bounds it
        out += ["## The TES nonlinearity, not found", "", check["sentence"], ""]
    out += ["## What the fit cannot explain", ""]
    if unexplained:
        out += [
            (
                "Significant structure left in the residual after the nominal adjustments "
                "and the selected effects; these are NOT forced onto a catalog effect:"
            ),
            "",
        ]
        out += [f"- {entry['text']}." for entry in unexplained]
    else:
        out.append("Nothing: no line, band, time segment or sky region above 5 sigma is left.")
    out += ["", "## Nominal-model adjustments (fitted on every recording, not effects)", ""]
    out += [
        "| detector | quantity | value | sigma | unit | nominal |",
        "|---|---|---|---|---|---|",
    ]
    for det, items in result.get("nominal_adjustments", {}).items():
        for quantity, item in items.items():
            sigma = item["sigma"]
            sigma_text = f"{sigma:.3g}" if sigma is not None else "-"
            out.append(
                f"| {det} | {quantity} | {item['value']:.6g} | {sigma_text} | {item['unit']} | "
                f"{item['nominal']:.6g} |"
            )
    out += [
        "",
        "## Selection steps",
        "",
        "| step | added | removed | chi2 before | chi2 after | BIC before | BIC after | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in result["steps"]:
        out.append(
            f"| {s['step']} | {s['added'] or ''} | {s['removed'] or ''} | {s['chi2_before']:.1f} | "
            f"{s['chi2_after']:.1f} | {s['bic_before']:.1f} | {s['bic_after']:.1f} | {s['note']} |"
        )
    out += [
        "",
        "## Lines in the residual (before and after the fit)",
        "",
        (
            "Amplitudes of the static part of each line; *modulation* is the rms of its slow "
            "amplitude change over the recording (a drifting line)."
        ),
        "",
        (
            "| detector | frequency [Hz] | identification | before | significance | modulation "
            "| after | significance |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for line in result["lines"]:
        out.append(
            f"| {line['detector']} | {line['freq_hz']:.6f} | {line['identification']} | "
            f"{format_temperature(line['amplitude_before_k'])} | {line['significance_before_sigma']:.1f} | "
            f"{format_temperature(line['modulation_before_k'])} ({line['modulation_significance_sigma']:.1f} "
            f"sigma) | {format_temperature(line['amplitude_after_k'])} | {line['significance_after_sigma']:.1f} |"
        )
    out += ["", "## Noise (configured vs estimated from the residual, then as finally fitted)", ""]
    for nominal, estimated, det in zip(
        result["noise"]["nominal"], result["noise"]["estimated"], rec["detectors"], strict=False
    ):
        out.append(
            f"- {det}: NET {estimated['net_k_sqrt_s'] * 1e6:.2f} uK sqrt(s) (configured "
            f"{nominal['net_k_sqrt_s'] * 1e6:.2f}), f_knee {estimated['fknee_hz'] * 1e3:.3g} mHz "
            f"(configured {nominal['fknee_hz'] * 1e3:.3g}), alpha {estimated['alpha']:.2f} "
            f"(configured {nominal['alpha']:.2f})"
        )
    for final, det in zip(result["noise"].get("final", []), rec["detectors"], strict=False):
        out.append(
            f"- {det}, as the final fit weighs it (beside the effects found): NET "
            f"{final['net_k_sqrt_s'] * 1e6:.2f} uK sqrt(s), f_knee {final['fknee_hz'] * 1e3:.3g} "
            f"mHz, alpha {final['alpha']:.2f}"
        )
    if figure_files or figures_error:
        out += ["", "## Figures", ""]
        for title, name in (figure_files or {}).items():
            out.append(f"![{title}]({name})")
        if figures_error:
            out.append(f"The figures could not be drawn ({figures_error}); the log has the trace.")
    return "\n".join(out) + "\n"


COINCIDENCES_LISTED = 10  # coincident events named in the scope's sentence


def scope_lines(effect: dict, n_detectors: int) -> list[str]:
    """The report's scope lines of an effect: its ``scope``, or one per segment
    (``scope_per_segment``, a recording diagnosed in segments whose scopes differ)."""
    out = []
    if "scope" in effect:
        out += [f"*Scope*: {scope_sentence(effect['scope'], n_detectors)}.", ""]
    for index, scope in effect.get("scope_per_segment", {}).items():
        out += [f"*Scope in segment {index}*: {scope_sentence(scope, n_detectors)}.", ""]
    return out


def scope_sentence(scope: dict, n_detectors: int) -> str:
    """Which detectors share an effect's parameters (:meth:`.effects.base.Effect.scope`)."""
    if scope["by"] == "detector":
        return f"each of the {n_detectors} detectors its own parameters"
    if scope["by"] == "pair":
        return "a coupling per pair of detectors"
    if scope["by"] == "coincidence":
        shown = list(scope["groups"].items())[:COINCIDENCES_LISTED]
        listed = ", ".join(f"{label} ({', '.join(names)})" for label, names in shown)
        more = len(scope["groups"]) - len(shown)
        return (
            f"events shared across detectors, at one time each: {listed}"
            + (f" and {more} more" if more > 0 else "")
            + f" ({scope['observed_pairs']} coincident detector pairs, chance expects "
            f"{scope['expected_pairs']:.2g}, p = {scope['p_value']:.2g}); the others per detector"
        )
    if scope["by"] == "all":
        return f"one set of parameters for all {n_detectors} detectors"
    groups = ", ".join(
        f"{label} ({', '.join(names) if len(names) <= 8 else f'{len(names)} detectors'})"
        for label, names in scope["groups"].items()
    )
    return f"one set of parameters per {scope['by']}: {groups}"


def parameter_table(parameters: dict, max_rows: int = 100) -> list[str]:
    """An effect's parameters as a table, a row per detector (or group, "common", or a
    detector's event) and a column per parameter, "value +- sigma" (sigma "-" where the fit
    gives none)."""

    def cell(entry):
        sigma = entry.get("sigma")
        sigma_text = f"{sigma:.2g}" if sigma is not None else "-"
        return f"{entry['value']:.6g} +- {sigma_text}"

    if not all("detector" in e and "parameter" in e for e in parameters.values()):
        lines = ["| parameter | value | unit |", "|---|---|---|"]
        return lines + [f"| {name} | {cell(e)} | {e['unit']} |" for name, e in parameters.items()]
    columns = {e["parameter"]: e["unit"] for e in parameters.values()}
    rows: dict[str, dict] = {}
    for name, entry in parameters.items():
        # a row per detector, or per detector and event ("glitch3.amplitude[<detector>]")
        head = name.split("[", 1)[0]
        event = head[: -len(entry["parameter"])].rstrip(".") if head != entry["parameter"] else ""
        rows.setdefault(f"{entry['detector']} {event}".strip(), {})[entry["parameter"]] = entry
    header = " | ".join(f"{p} [{unit}]" for p, unit in columns.items())
    lines = [f"| detector | {header} |", "|---" * (len(columns) + 1) + "|"]
    for detector, entries in list(rows.items())[:max_rows]:
        cells = " | ".join(cell(entries[p]) if p in entries else "" for p in columns)
        lines.append(f"| {detector} | {cells} |")
    if len(rows) > max_rows:
        lines.append(f"| ... {len(rows) - max_rows} more rows in diagnosis.json | |")
    return lines
