"""Readout steps: a detector's offset and gain jumping at one time (a SQUID's flux jump, a
bias-line step, a readout reset), the catalog effect. Detector k's recording after a step
at t_s (the first sample after it):

    d_rec(t) = d(t) + H(t - t_s) [o + s d(t)],

o the offset jump [K], s the relative gain jump (dimensionless), d the detector's signal
(the nominal TOD d_nom: HWPSS, sky, dipole). The gain part is a jump of the 2f HWPSS
amplitude by s A_2 at t_s; the offset part a step in the low frequencies. The scan and
the sharpness test are in :mod:`.step_scan`, the exact fit in :mod:`.step_fit`, the
search in :mod:`.step_search`, a bias line's one time in :mod:`.step_lines`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import numpy as np

from ..fourier import rfft
from .base import Effect, format_temperature, register
from .event_groups import coincidence_scope, coincidence_sentence, coincidences
from .step_lines import line_time, steps_at_shared_time
from .step_scan import RAMP_S
from .step_search import StepEvent, StepSearch, find_steps, step_tod

__all__ = ["ReadoutSteps", "StepEvent", "find_steps", "step_coincidences", "step_tod"]


@register
class ReadoutSteps(Effect):
    """Readout steps: d -> d + H(t - t_s) [o + s d] per detector and step.

    A SQUID's flux jump moves the offset (o); a step of the TES bias or of the readout's
    gain moves the responsivity (s), seen as a jump of the 2f HWPSS amplitude by s A_2.
    Found by a scan of the residual over the step's time (both parts, noise-weighted),
    fitted exactly at the best time, its parts (offset, gain or both) those the BIC
    prefers, kept while each pays ln N per part and 2 ln N for its time. Where detectors
    step together beyond chance (a bias line), every other detector is fitted at that
    time, and keeps a step where its parts alone pay.
    """

    name = "readout_steps"
    title = "readout steps (offset and gain jumps)"
    parameters: ClassVar[dict[str, str]] = {"offset": "K", "gain": "", "time": "s"}
    events: ClassVar[bool] = True
    main_parameters = ("offset", "gain")
    kind = "events"
    stage = "events"
    after_noise_refit: ClassVar[bool] = True
    signature = (
        "the offset and the 2f HWPSS amplitude jumping at one time and staying there, "
        "in one detector or in the detectors of one bias line at once"
    )
    discrimination = (
        "a gain drift (gain_drift) moves the 2f amplitude smoothly over the recording, a "
        "step at one sample; a gain fluctuation (gain_fluctuations) is a random walk of "
        "many small moves, a step one move the scan localises; a glitch decays back, a "
        "step stays; 1/f noise has no preferred time, a step's delta chi^2 peaks at one"
    )

    def find(self, problem, k: int, r_f: np.ndarray, bank=None, gram=None) -> list[StepEvent]:
        """The steps in detector k's residual ``r_f`` (:func:`find_steps` with the
        problem's weights and ln N_eff), fitted jointly with the linear templates ``bank``
        (rfft rows) of Gram matrix ``gram``."""
        search = self._search(problem, k)
        return find_steps(r_f, search, k, problem.ln_n_eff, bank=search.bank(bank, gram))

    def _search(self, problem, k: int) -> StepSearch:
        """Detector k's :class:`.step_search.StepSearch`, once per detector and noise model."""
        search = problem.derived.get((self.name, k))
        if search is None:
            ctx = problem.ctx
            search = StepSearch.of(
                problem.w_nom[k], problem.valid[k], ctx.d_nom[k], ctx.times_s, ctx.f_hwp_hz
            )
            problem.derived[(self.name, k)] = search
        return search

    def complete_events(self, problem, events, residual_of) -> list:
        """``events`` (every detector's, as :meth:`find` gave them) and the steps at a bias
        line's time in its other detectors: where steps coincide beyond chance
        (:func:`step_coincidences`), the group's steps are put at the line's one time
        (:func:`.step_lines.line_time`) and each detector outside it is fitted at that
        time (:func:`.step_lines.steps_at_shared_time`), its
        residual ``residual_of(k)`` = (rfft as :meth:`find` takes it, bank, gram) less its
        own steps. A step too weak to be found at an unknown time is found at a known one."""
        ctx = problem.ctx
        if ctx.n_detectors < 3 or len(events) < 2:
            return events
        found = step_coincidences(events, ctx)
        if not found.significant:
            return events
        events, added = list(events), []

        def without_own(k, but=None):  # detector k's residual less its steps but ``but``
            r_f, bank, gram = residual_of(k)
            own = [
                StepEvent(**{**e.__dict__, "detector": 0})
                for e in events
                if e.detector == k and e is not but
            ]
            if own:  # the detector's own steps, as its search subtracted them
                tod = step_tod(ctx.times_s, ctx.d_nom[k : k + 1], own)[0]
                r_f = r_f - rfft(tod * problem.valid[k], workers=problem.workers)
            return r_f, self._search(problem, k).bank(bank, gram)

        for group, detectors in zip(found.groups, found.detectors, strict=True):
            members = []  # the line's steps, to be put at its one time (:func:`line_time`)
            for i in group:
                k = events[i].detector
                r_f, bank = without_own(k, but=events[i])
                members.append((events[i], r_f, self._search(problem, k), bank))
            line_events = line_time(members, ctx.sampling_rate_hz)
            for i, event in zip(group, line_events, strict=True):
                events[i] = event
            line = max(line_events, key=lambda e: e.significance)
            for k in range(ctx.n_detectors):
                if k in detectors:
                    continue
                r_f, bank = without_own(k)
                event = steps_at_shared_time(
                    r_f, self._search(problem, k), k, line, problem.ln_n_eff, bank
                )
                if event is not None:
                    added.append(event)
        return events + added

    @staticmethod
    def detector_events(ctx, events) -> list:
        return events

    @staticmethod
    def events_tod(ctx, events) -> np.ndarray:
        """The steps' TOD on the nominal signal, (n_det, n): :func:`step_tod`."""
        return step_tod(ctx.times_s, ctx.d_nom, events)

    def before_events(self, fit, ctx, a2_before_k):
        """The gain jumps relative to the signal before the steps: the template s d_nom has
        the adjusted A_2, which holds part of the steps (A_2 (1 + s f_after) for one step
        a fraction f_after from the end), so s = s_fit A_2,adjusted / A_2,before, the value
        and its error."""
        scale = np.asarray(ctx.a2_k, dtype=float) / np.asarray(a2_before_k, dtype=float)
        events = [
            StepEvent(
                **{
                    **e.__dict__,
                    "gain": e.gain * scale[e.detector],
                    "sigma_gain": e.sigma_gain * scale[e.detector],
                }
            )
            for e in fit.events
        ]
        return dataclasses.replace(fit, events=events)

    def reported_parameters(self, fit, detector_names, sampling_rate_hz, units) -> dict:
        """Per step i: "step<i>.offset|gain|time[<detector>]" (the parts it was fitted
        with, and its time), in detector and time order."""
        out = {}
        for i, e in enumerate(sorted(fit.events, key=lambda e: (e.detector, e.time_s))):
            det = detector_names[e.detector]
            values = {
                "offset": (e.offset_k, e.sigma_offset_k, "K"),
                "gain": (e.gain, e.sigma_gain, ""),
                "time": (e.time_s, max(e.sigma_time_s, 0.5 / sampling_rate_hz), "s"),
            }
            for parameter in (*e.parts, "time"):
                value, sigma, unit = values[parameter]
                out[f"step{i}.{parameter}[{det}]"] = {
                    "value": value,
                    "sigma": sigma,
                    "unit": unit,
                    "detector": det,
                    "parameter": parameter,
                }
        return out

    def apply(self, ctx, params, tod=None):
        """``params``: {"events": [(detector, time_s, offset_k, gain), ...]}; the gain
        multiplies ``tod`` (default d_nom) itself."""
        tod = ctx.d_nom if tod is None else tod
        events = [e if isinstance(e, StepEvent) else StepEvent(*e) for e in params["events"]]
        return tod + step_tod(ctx.times_s, tod, events)

    def evidence(self, ev, fit) -> str:
        events = fit.events
        if not events:
            return "no step left after the fit"
        names = ev.ctx.detector_names
        strongest = max(events, key=lambda e: e.significance)

        def described(e) -> str:
            said = []
            if "offset" in e.parts and e.sigma_offset_k > 0:
                said.append(
                    f"offset {format_temperature(e.offset_k)} "
                    f"({abs(e.offset_k) / e.sigma_offset_k:.0f} sigma)"
                )
            if "gain" in e.parts and e.sigma_gain > 0:
                said.append(f"gain {e.gain:+.2e} ({abs(e.gain) / e.sigma_gain:.0f} sigma)")
            unresolved = "" if e.sharp else f" (not told apart from a change over {RAMP_S:.0f} s)"
            timed = " (at its line's time)" if e.shared_time else ""
            return (
                f"{names[e.detector]} at t = {e.time_s:.1f} +- {e.sigma_time_s:.1g} s{timed}: "
                + ", ".join(said)
                + unresolved
            )

        listed = "; ".join(described(e) for e in sorted(events, key=lambda e: -e.significance)[:5])
        smooth = sum(not e.sharp for e in events)
        at_line = sum(e.completed for e in events)
        return (
            f"{len(events)} step(s), the strongest {strongest.significance:.0f} sigma: {listed}; "
            "each stays after its time (no decay)"
            + (
                f"; {at_line} of them found at the time of a step the other detectors of a "
                "line share (fitted there, too weak to be found at an unknown time)"
                if at_line
                else ""
            )
            + (
                f"; {smooth} of them not told apart from a smooth change over {RAMP_S:.0f} s "
                "(a drift's or a modulation's edge fits them as well)"
                if smooth
                else ""
            )
            + (
                "; " + coincidence_sentence(step_coincidences(events, ev.ctx))
                if len(names) > 1
                else ""
            )
        )

    def scope(self, ctx, fit=None) -> dict:
        """Per detector, or by coincidence where steps of several detectors share a time
        more than chance (a bias line's step): as the glitches' scope."""
        if fit is None or ctx.n_detectors < 2 or not fit.events:
            return super().scope(ctx)
        found = step_coincidences(fit.events, ctx)
        if not found.significant:
            return super().scope(ctx)
        return coincidence_scope(found, fit.events, ctx.detector_names)


def step_coincidences(events, ctx):
    """:func:`.event_groups.coincidences` of steps, linked within 3 sqrt(2) times the
    largest step time error (a step is timed to its scan's cusp, not to a sample)."""
    widest_s = max(e.sigma_time_s for e in events)
    window = max(1, math.ceil(3 * math.sqrt(2) * widest_s * ctx.sampling_rate_hz))
    return coincidences(events, ctx.times_s, ctx.valid, window)
