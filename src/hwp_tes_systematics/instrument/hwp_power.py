"""Optical power from the 20 K metal-mesh HWP and the HWP synchronous signal amplitude A_2.

Along each HWP axis x (capacitive c, inductive i) the detector sees, through the
optics downstream of the HWP (efficiency eta_down, elements after the HWP):

    P_emis,x  = eta_down  integral w a_x(nu) h nu n(nu, T_HWP) d nu     (gray-body emission)
    P_trans,x = eta_down  integral w t_x(nu) h nu n(nu, T_load) d nu    (incoming sky/CMB load)
    P_chain   = sum_j integral w eps_j h nu n(nu, T_j) d nu  prod_{k>j} eta_k  (optics after HWP)

As the HWP turns by chi, the detector's polarisation sweeps from one axis to the
other, so the load carries a 2 chi modulation of amplitude set by

    Delta P_HWP = (P_emis,c - P_emis,i) + (P_trans,c - P_trans,i),
    A_2 = (a2_over_delta_p) Delta P_HWP   (paper: A_2 = Delta P_HWP, a2_over_delta_p = 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .radiometry import Bandpass, channel_bandpass, single_mode_spectral_power_w_per_hz

CURVE_COLUMNS = (
    "freq_ghz",
    "absorption_capacitive",
    "absorption_inductive",
    "transmission_capacitive",
    "transmission_inductive",
)


class HwpCurveError(ValueError):
    """A HWP absorption/transmission table is missing or malformed."""


@dataclass(frozen=True)
class HwpCurves:
    """Per-axis absorption a(nu) and transmission t(nu) of a HWP."""

    freqs_ghz: np.ndarray
    absorption_capacitive: np.ndarray
    absorption_inductive: np.ndarray
    transmission_capacitive: np.ndarray
    transmission_inductive: np.ndarray
    source: str = "ideal"

    @classmethod
    def ideal(cls) -> HwpCurves:
        """A lossless, perfectly transmitting HWP: no emission, no differential load."""
        freqs = np.array([1.0, 1e4])
        zeros, ones = np.zeros(2), np.ones(2)
        return cls(freqs, zeros, zeros, ones, ones, source="ideal")

    def on(self, freqs_ghz: np.ndarray) -> dict[str, np.ndarray]:
        """The four curves linearly interpolated onto ``freqs_ghz``."""
        low, high = freqs_ghz.min(), freqs_ghz.max()
        if low < self.freqs_ghz[0] - 1e-9 or high > self.freqs_ghz[-1] + 1e-9:
            raise HwpCurveError(
                f"{self.source}: tabulated from {self.freqs_ghz[0]:g} to "
                f"{self.freqs_ghz[-1]:g} GHz, but a band needs {low:g}-{high:g} GHz; "
                "extend the table to cover every channel of its telescope"
            )
        return {
            name: np.interp(freqs_ghz, self.freqs_ghz, getattr(self, name))
            for name in CURVE_COLUMNS[1:]
        }


def read_hwp_curves(path: str | Path) -> HwpCurves:
    """Read a HWP curve table (CSV, '#' comments) with the columns of CURVE_COLUMNS.

    Checks: the file exists and parses, every column is present and numeric,
    frequencies strictly increase, 0 <= a, t and a + t <= 1 on each axis.
    """
    path = Path(path)
    if not path.is_file():
        raise HwpCurveError(f"HWP curve table {path}: file not found")
    try:
        table = pd.read_csv(path, comment="#", skipinitialspace=True)
    except Exception as error:
        raise HwpCurveError(f"HWP curve table {path}: cannot parse as CSV ({error})") from error
    missing = [column for column in CURVE_COLUMNS if column not in table.columns]
    if missing:
        raise HwpCurveError(
            f"HWP curve table {path}: missing column(s) {missing}; expected columns "
            f"{list(CURVE_COLUMNS)}"
        )
    values = {}
    for column in CURVE_COLUMNS:
        numeric = pd.to_numeric(table[column], errors="coerce").to_numpy(dtype=float)
        if not np.all(np.isfinite(numeric)):
            bad_row = int(np.flatnonzero(~np.isfinite(numeric))[0])
            raise HwpCurveError(
                f"HWP curve table {path}: column {column!r} row {bad_row} is "
                f"{table[column].iloc[bad_row]!r}; expected a finite number"
            )
        values[column] = numeric
    if len(values["freq_ghz"]) < 2 or np.any(np.diff(values["freq_ghz"]) <= 0):
        raise HwpCurveError(
            f"HWP curve table {path}: freq_ghz must have >= 2 strictly increasing values"
        )
    for axis in ("capacitive", "inductive"):
        absorption = values[f"absorption_{axis}"]
        transmission = values[f"transmission_{axis}"]
        if np.any(absorption < 0) or np.any(transmission < 0):
            raise HwpCurveError(
                f"HWP curve table {path}: negative absorption or transmission on the "
                f"{axis} axis; expected values in [0, 1]"
            )
        if np.any(absorption + transmission > 1 + 1e-9):
            raise HwpCurveError(
                f"HWP curve table {path}: absorption + transmission > 1 on the {axis} "
                "axis (energy conservation: a + t + reflection = 1)"
            )
    return HwpCurves(
        freqs_ghz=values["freq_ghz"],
        absorption_capacitive=values["absorption_capacitive"],
        absorption_inductive=values["absorption_inductive"],
        transmission_capacitive=values["transmission_capacitive"],
        transmission_inductive=values["transmission_inductive"],
        source=str(path),
    )


@dataclass(frozen=True)
class OpticalElement:
    """An element of the optical chain after the HWP (sky side first)."""

    name: str
    temperature_k: float
    emissivity: float
    efficiency: float


def efficiency_after(elements: list[OpticalElement], index: int) -> float:
    """prod of the efficiencies of elements index+1 ... (towards the detector)."""
    return float(np.prod([element.efficiency for element in elements[index + 1 :]]))


def downstream_efficiency(elements: list[OpticalElement]) -> float:
    """eta_down = prod of all element efficiencies after the HWP."""
    return efficiency_after(elements, -1)


def chain_emission_w(bandpass: Bandpass, elements: list[OpticalElement]) -> float:
    """P_chain = sum_j eps_j integral w h nu n(nu, T_j) d nu prod_{k>j} eta_k [W]."""
    total_w = 0.0
    for index, element in enumerate(elements):
        if element.emissivity == 0.0:
            continue
        spectral = single_mode_spectral_power_w_per_hz(bandpass.freqs_ghz, element.temperature_k)
        total_w += (
            element.emissivity * efficiency_after(elements, index) * bandpass.integrate(spectral)
        )
    return total_w


def hwp_power_for_channel(
    channel,
    curves: HwpCurves,
    hwp_temperature_k: float,
    elements: list[OpticalElement],
    incoming_load_temperature_k: float,
    a2_over_delta_p: float = 1.0,
) -> dict:
    """Per-axis HWP emission and transmitted load, Delta P_HWP and A_2 for one channel [W]."""
    bandpass = channel_bandpass(channel)
    on_band = curves.on(bandpass.freqs_ghz)
    eta_down = downstream_efficiency(elements)
    hwp_spectral = single_mode_spectral_power_w_per_hz(bandpass.freqs_ghz, hwp_temperature_k)
    load_spectral = single_mode_spectral_power_w_per_hz(
        bandpass.freqs_ghz, incoming_load_temperature_k
    )

    row = {
        "channel": channel.name,
        "telescope": channel.telescope,
        "bandcenter_ghz": channel.bandcenter_ghz,
        "bandwidth_ghz": channel.bandwidth_ghz,
        "hwp_curves": curves.source,
        "hwp_temperature_k": hwp_temperature_k,
        "downstream_efficiency": eta_down,
    }
    for axis in ("capacitive", "inductive"):
        absorption = on_band[f"absorption_{axis}"]
        transmission = on_band[f"transmission_{axis}"]
        row[f"band_mean_absorption_{axis}"] = bandpass.integrate(absorption) / bandpass.integrate(
            np.ones_like(absorption)
        )
        row[f"p_emission_{axis}_w"] = eta_down * bandpass.integrate(absorption * hwp_spectral)
        row[f"p_transmitted_{axis}_w"] = eta_down * bandpass.integrate(transmission * load_spectral)

    row["delta_p_emission_w"] = row["p_emission_capacitive_w"] - row["p_emission_inductive_w"]
    row["delta_p_transmission_w"] = (
        row["p_transmitted_capacitive_w"] - row["p_transmitted_inductive_w"]
    )
    row["delta_p_hwp_w"] = row["delta_p_emission_w"] + row["delta_p_transmission_w"]
    row["p_chain_w"] = chain_emission_w(bandpass, elements)
    for axis in ("capacitive", "inductive"):
        row[f"p_total_{axis}_w"] = (
            row[f"p_emission_{axis}_w"] + row[f"p_transmitted_{axis}_w"] + row["p_chain_w"]
        )
    row["p_nominal_w"] = 0.5 * (row["p_total_capacitive_w"] + row["p_total_inductive_w"])
    row["a2_over_delta_p"] = a2_over_delta_p
    row["a2_w"] = a2_over_delta_p * row["delta_p_hwp_w"]
    return row


def sky_to_detector_efficiency(channel, curves: HwpCurves, elements: list[OpticalElement]):
    """eta(nu) = (t_c + t_i)/2 eta_down on the channel's band: the CMB's path to the detector."""
    bandpass = channel_bandpass(channel)
    on_band = curves.on(bandpass.freqs_ghz)
    mean_transmission = 0.5 * (
        on_band["transmission_capacitive"] + on_band["transmission_inductive"]
    )
    return bandpass, mean_transmission * downstream_efficiency(elements)


# Assumed curves for the MFT and HFT metal-mesh HWPs (the paper shows them only as
# plots). Shape: dielectric (polypropylene) loss gives absorption a = 2 pi n tan(delta)
# d nu / c, linear in frequency; the capacitive axis, whose field concentrates in the
# dielectric between patches, absorbs about twice the inductive one. The HFT plate is
# thinner in proportion to its design wavelength, so both plates absorb the same at their
# own reference frequency (150 and 300 GHz). Reflection is a residual anti-reflection
# ripple; the capacitive axis reflects less by 90 % of its
# extra absorption, so the differential transmission is ~10 % of the differential
# absorption and Delta P is dominated by emission, as the paper states for MHFT.
ASSUMED_HWP_DESIGNS = {
    # telescope: (f_min, f_max, step [GHz], nu_ref [GHz], a_ind(nu_ref), a_cap(nu_ref),
    #             mean reflection, ripple amplitude, ripple period [GHz])
    "MFT": (70.0, 270.0, 1.0, 150.0, 0.010, 0.020, 0.03, 0.01, 60.0),
    "HFT": (150.0, 520.0, 2.0, 300.0, 0.010, 0.020, 0.04, 0.01, 120.0),
}
CAPACITIVE_REFLECTION_COMPENSATION = 0.9


def assumed_metal_mesh_curves(telescope: str) -> pd.DataFrame:
    """The assumed per-axis curves (see ASSUMED_HWP_DESIGNS) as a table of CURVE_COLUMNS."""
    f_min, f_max, step, nu_ref, a_ind_ref, a_cap_ref, r_mean, r_ripple, period = (
        ASSUMED_HWP_DESIGNS[telescope]
    )
    freqs_ghz = np.arange(f_min, f_max + step / 2, step)
    absorption_inductive = a_ind_ref * freqs_ghz / nu_ref
    absorption_capacitive = a_cap_ref * freqs_ghz / nu_ref
    reflection_inductive = r_mean + r_ripple * np.cos(2 * np.pi * (freqs_ghz - nu_ref) / period)
    reflection_capacitive = reflection_inductive - CAPACITIVE_REFLECTION_COMPENSATION * (
        absorption_capacitive - absorption_inductive
    )
    return pd.DataFrame(
        {
            "freq_ghz": freqs_ghz,
            "absorption_capacitive": absorption_capacitive,
            "absorption_inductive": absorption_inductive,
            "transmission_capacitive": 1 - absorption_capacitive - reflection_capacitive,
            "transmission_inductive": 1 - absorption_inductive - reflection_inductive,
        }
    ).round(6)
