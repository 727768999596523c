"""Figures of the HWP stage: the paper's Figs. 1, 2 and 3."""

from __future__ import annotations

import numpy as np
import pandas as pd
from pysm3.models.dust import blackbody_nu

from . import save_figure, subplots

AXIS_COLORS = {"capacitive": "tab:blue", "inductive": "tab:purple"}
MJY_PER_SR_PER_SI = 1e20  # 1 W m^-2 Hz^-1 sr^-1 = 1e26 Jy/sr = 1e20 MJy/sr

# Brightest Galactic dust for Fig. 3: a modified black body with the pysm3 d0 SED
# (beta = 1.54, T = 20 K) normalised to the order of the maximum of the Planck 353 GHz
# intensity map and of the pysm3 d0 template in the Galactic plane (assumption; figure only).
DUST_MAX_353GHZ_MJY_PER_SR = 1000.0
DUST_BETA, DUST_TEMPERATURE_K = 1.54, 20.0


def _telescope_rows(table: pd.DataFrame, telescope: str) -> pd.DataFrame:
    return table[table["telescope"] == telescope]


def plot_curves(curves: dict, table: pd.DataFrame, path) -> None:
    """Fig. 1: per-axis absorption (top) and transmission (bottom), MFT left, HFT right."""
    fig, axes = subplots(2, len(curves), figsize=(5.5 * len(curves), 6.5), sharex="col")
    axes = np.atleast_2d(axes).reshape(2, len(curves))
    for column, (telescope, hwp) in enumerate(curves.items()):
        for row, quantity in enumerate(("absorption", "transmission")):
            ax = axes[row, column]
            for axis_name, color in AXIS_COLORS.items():
                ax.plot(
                    hwp.freqs_ghz,
                    getattr(hwp, f"{quantity}_{axis_name}"),
                    color=color,
                    label=axis_name,
                )
            for center in _telescope_rows(table, telescope)["bandcenter_ghz"]:
                ax.axvline(center, color="gray", ls="--", lw=0.8)
            ax.set_ylabel(quantity)
            ax.grid(alpha=0.3)
        axes[0, column].set_title(f"{telescope} HWP ({hwp.source.split('/')[-1]})")
        axes[1, column].set_xlabel("frequency [GHz]")
        axes[0, column].legend()
    save_figure(fig, path)


def plot_differential_power(table: pd.DataFrame, path) -> None:
    """Fig. 2: |Delta P| from differential absorption and transmission over P_inductive [%]."""
    telescopes = [t for t in ("MFT", "HFT") if (table["telescope"] == t).any()]
    fig, axes = subplots(1, max(len(telescopes), 1), figsize=(5.5 * max(len(telescopes), 1), 4))
    axes = np.atleast_1d(axes)
    for ax, telescope in zip(axes, telescopes):
        rows = _telescope_rows(table, telescope)
        x = np.arange(len(rows))
        for offset, column, color, label in (
            (-0.2, "delta_p_emission_w", "tab:red", "differential absorption (emission)"),
            (0.2, "delta_p_transmission_w", "tab:blue", "differential transmission"),
        ):
            percent = 100 * rows[column].to_numpy() / rows["p_total_inductive_w"].to_numpy()
            bars = ax.bar(x + offset, np.abs(percent), width=0.4, color=color, label=label)
            for bar, value in zip(bars, percent):
                if value < 0:
                    bar.set_hatch("//")
        ax.set_yscale("log")
        ax.set_xticks(x, rows["channel"], rotation=45)
        ax.set_ylabel(r"$|\Delta P_\mathrm{opt}| / P_\mathrm{ind}$ [%]  (hatched: negative)")
        ax.set_title(telescope)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    save_figure(fig, path)


def plot_emission_vs_sky(
    curves: dict, hwp_temperature_k: dict, table: pd.DataFrame, t_cmb_k: float, path
) -> None:
    """Fig. 3: HWP gray-body a_x B_nu(T_HWP) per axis vs the CMB and the brightest dust [MJy/sr]."""
    fig, axes = subplots(1, len(curves), figsize=(5.5 * len(curves), 4))
    axes = np.atleast_1d(axes)
    for ax, (telescope, hwp) in zip(axes, curves.items()):
        freqs_ghz = hwp.freqs_ghz
        planck_hwp = blackbody_nu(freqs_ghz, hwp_temperature_k[telescope]) * MJY_PER_SR_PER_SI
        ax.plot(
            freqs_ghz,
            hwp.absorption_inductive * planck_hwp,
            color="tab:blue",
            label=f"HWP {hwp_temperature_k[telescope]:g} K, inductive",
        )
        ax.plot(
            freqs_ghz,
            hwp.absorption_capacitive * planck_hwp,
            color="tab:orange",
            label=f"HWP {hwp_temperature_k[telescope]:g} K, capacitive",
        )
        ax.plot(
            freqs_ghz,
            blackbody_nu(freqs_ghz, t_cmb_k) * MJY_PER_SR_PER_SI,
            color="tab:red",
            label=f"CMB {t_cmb_k:g} K",
        )
        dust = (
            DUST_MAX_353GHZ_MJY_PER_SR
            * (freqs_ghz / 353.0) ** DUST_BETA
            * blackbody_nu(freqs_ghz, DUST_TEMPERATURE_K)
            / blackbody_nu(353.0, DUST_TEMPERATURE_K)
        )
        ax.plot(freqs_ghz, dust, color="tab:purple", ls="--", label="max Galactic dust (MBB)")
        for center in _telescope_rows(table, telescope)["bandcenter_ghz"]:
            ax.axvline(center, color="gray", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("frequency [GHz]")
        ax.set_ylabel(r"spectral radiance $I_\nu$ [MJy/sr]")
        ax.set_title(telescope)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, path)
