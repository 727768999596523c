"""TES response curve I(P_opt) and responsivity S(P_opt) (cf. Fig. 4 of the study).

The detector saturates (goes normal) as the optical power increases; the nominal
optical power of the channel and its variation range in the presence of the HWP
synchronous signal (HWPSS) are marked.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..instrument.tes import (
    TesParameters,
    optical_power_for_resistance,
    responsivity_a_per_w,
    solve_operating_point,
)
from . import save_figure, subplots

_PW_PER_W = 1e12
_UA_PER_A = 1e6
_UA_PER_PW_PER_A_PER_W = _UA_PER_A / _PW_PER_W


def plot_response_curve(
    params: TesParameters,
    p_nominal_w: float,
    hwpss_amplitude_w: float,
    channel_name: str,
    path: str | os.PathLike,
) -> Path:
    """Plot I [uA] and S = dI/dP_opt [uA/pW] versus P_opt [pW] from ~0 to 1.2 Psat.

    Marks the nominal power, the band nominal +- ``hwpss_amplitude_w``, Psat and the
    optical saturation power (R = 0.99 Rn). Writes the PNG atomically and returns its path.
    """
    path = Path(path)
    powers_w = np.linspace(0.005, 1.2, 480) * params.psat_w
    currents_a = solve_operating_point(params, powers_w).current_a
    responsivities_a_per_w = responsivity_a_per_w(params, powers_w)
    p_normal_w = optical_power_for_resistance(params, 0.99)

    figure, (current_axis, responsivity_axis) = subplots(2, 1, figsize=(7.0, 6.5), sharex=True)
    current_axis.plot(powers_w * _PW_PER_W, currents_a * _UA_PER_A, color="C0")
    current_axis.set_ylabel("TES current I [uA]")
    current_axis.set_title(f"{channel_name}: TES response (steady-state electrothermal model)")
    responsivity_axis.plot(
        powers_w * _PW_PER_W, responsivities_a_per_w * _UA_PER_PW_PER_A_PER_W, color="C0"
    )
    responsivity_axis.set_ylabel("responsivity S = dI/dP [uA/pW]")
    responsivity_axis.set_xlabel("optical power P_opt [pW]")

    for axis in (current_axis, responsivity_axis):
        axis.axvspan(
            (p_nominal_w - hwpss_amplitude_w) * _PW_PER_W,
            (p_nominal_w + hwpss_amplitude_w) * _PW_PER_W,
            color="C1",
            alpha=0.25,
            label="nominal +- HWPSS",
        )
        axis.axvline(p_nominal_w * _PW_PER_W, color="C1", label="nominal P_opt")
        axis.axvline(
            p_normal_w * _PW_PER_W, color="C3", linestyle=":", label="normal (R = 0.99 Rn)"
        )
        axis.axvline(params.psat_w * _PW_PER_W, color="k", linestyle="--", label="Psat")
        axis.grid(alpha=0.3)
    current_axis.legend(loc="upper right", fontsize="small")

    save_figure(figure, path)
    return path
