"""Figures of the TOD stage: the paper's Figs. 5 and 6, and the notch transfer function."""

from __future__ import annotations

import numpy as np

from ..simulation.notch import notch_edges_hz, notch_transfer, notch_width_hz
from ..simulation.spectral import amplitude_spectrum
from . import save_figure, subplots


def plot_tod_chunk(times_s, tod_k, tod_nl_k, g1_per_k, channel_name, path, span_s=10.0) -> None:
    """Fig. 5: a chunk of TOD without and with the nonlinearity, and their difference [mK]."""
    shown = times_s - times_s[0] < span_s
    fig, (top, bottom) = subplots(
        2, 1, figsize=(8, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]}
    )
    top.plot(times_s[shown], 1e3 * tod_k[shown], label="input TOD d (sky + dipole + HWPSS + noise)")
    top.plot(
        times_s[shown],
        1e3 * tod_nl_k[shown],
        label=rf"$[1 + g_1 d]\,d$, $g_1$ = {g1_per_k:g} K$^{{-1}}$",
        alpha=0.8,
    )
    top.set_ylabel("TOD [mK$_\\mathrm{CMB}$]")
    top.set_title(f"{channel_name}: the 2 f_HWP HWPSS through the TES nonlinearity")
    top.legend(fontsize=8, loc="upper right")
    bottom.plot(times_s[shown], 1e3 * (tod_nl_k - tod_k)[shown], color="tab:red")
    bottom.set_ylabel(r"$g_1 d^2$ [mK]")
    bottom.set_xlabel("time [s]")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def plot_tod_spectra(
    tod_k, tod_nl_k, sampling_rate_hz, f_hwp_hz, f_spin_hz, g1_per_k, channel_name, path
) -> None:
    """Fig. 6: amplitude spectra without/with nonlinearity; zoom on 2 f_HWP +- f_dipole."""
    freqs, amplitude = amplitude_spectrum(tod_k, sampling_rate_hz)
    _, amplitude_nl = amplitude_spectrum(tod_nl_k, sampling_rate_hz)
    fig, (full, zoom) = subplots(2, 1, figsize=(8, 7))
    keep = freqs > 0
    full.loglog(freqs[keep], amplitude[keep], lw=0.6, label="without nonlinearity")
    full.loglog(
        freqs[keep],
        amplitude_nl[keep],
        lw=0.6,
        alpha=0.8,
        label=rf"with nonlinearity, $g_1$ = {g1_per_k:g} K$^{{-1}}$",
    )
    for harmonic, style in ((2, "--"), (4, ":")):
        full.axvline(harmonic * f_hwp_hz, color="gray", ls=style, lw=0.8, label=f"{harmonic} f_HWP")
    full.set_ylabel("amplitude [K]")
    full.set_xlabel("frequency [Hz]")
    full.set_title(f"{channel_name}: amplitude spectra")
    full.legend(fontsize=8)
    window = np.abs(freqs - 2 * f_hwp_hz) < 4 * f_spin_hz
    zoom.semilogy(freqs[window] - 2 * f_hwp_hz, amplitude[window], lw=0.8)
    zoom.semilogy(freqs[window] - 2 * f_hwp_hz, amplitude_nl[window], lw=0.8, alpha=0.8)
    for sign in (-1, 1):
        zoom.axvline(sign * f_spin_hz, color="tab:red", ls="--", lw=0.8)
    zoom.set_xlabel(
        r"$f - 2 f_\mathrm{HWP}$ [Hz]  (dashed: $\pm f_\mathrm{dipole}$ = spin frequency)"
    )
    zoom.set_ylabel("amplitude [K]")
    for ax in (full, zoom):
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def plot_notch_transfer(f_hwp_by_telescope: dict, width_divisor: float, path) -> None:
    """The notch F(f) around 4 f_HWP for each telescope (``width_divisor`` None: no notch,
    F = 1, drawn over +- 0.1 Hz)."""
    fig, ax = subplots(figsize=(7, 4))
    for telescope, f_hwp_hz in f_hwp_by_telescope.items():
        if width_divisor is None:
            freqs = 4 * f_hwp_hz + np.linspace(-0.1, 0.1, 3)
            ax.plot(freqs, np.ones(3), label=f"{telescope}: no notch (notch.width_divisor null)")
            continue
        delta_f = notch_width_hz(f_hwp_hz, width_divisor)
        f1, _, _, f4 = notch_edges_hz(f_hwp_hz, delta_f)
        freqs = np.linspace(f1 - 2 * delta_f, f4 + 2 * delta_f, 2000)
        ax.plot(
            freqs,
            notch_transfer(freqs, f_hwp_hz, delta_f),
            label=f"{telescope}: 4 f_HWP = {4 * f_hwp_hz:.3f} Hz, delta f = {delta_f:.4f} Hz",
        )
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("F(f)")
    ax.set_title("4 f_HWP notch filter (paper, section 4.1)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def plot_notch_effect(table, channel_name, f_hwp_hz, width_divisor, path) -> None:
    """Input CMB EE/BB with and without the notch, and the notch's transfer F_XX(ell)."""
    ell = table["ell"].to_numpy()
    keep = ell >= 2
    fig, (spectra, ratio) = subplots(2, 1, figsize=(7.5, 7), sharex=True)
    d_ell = ell * (ell + 1) / (2 * np.pi) * 1e12  # D_ell in uK^2
    curves = (
        ("cmb_ee_k2", "transfer_ee", "tab:blue", "CMB EE"),
        ("cmb_bb_k2", "transfer_bb", "tab:red", "CMB BB (lensing)"),
    )
    for spectrum, transfer, color, label in curves:
        spectra.loglog(ell[keep], (d_ell * table[spectrum])[keep], color=color, label=label)
        spectra.loglog(
            ell[keep],
            (d_ell * table[spectrum] * table[transfer])[keep],
            color=color,
            ls="--",
            label=f"{label} through the notch",
        )
    tensor = 0.01 * table["tensor_bb_r1_k2"] * table["transfer_bb"]
    spectra.loglog(
        ell[keep],
        (d_ell * 0.01 * table["tensor_bb_r1_k2"])[keep],
        color="tab:green",
        label="tensor BB, r = 0.01",
    )
    spectra.loglog(
        ell[keep],
        (d_ell * tensor)[keep],
        color="tab:green",
        ls="--",
        label="tensor BB, r = 0.01, through the notch",
    )
    spectra.set_ylabel(r"$D_\ell$ [$\mu$K$^2$]")
    spectra.set_ylim(1e-6, None)
    fsky = float(table["observed_fraction"].iloc[0])
    notch = (
        "no notch"
        if width_divisor is None
        else f"delta f = {notch_width_hz(f_hwp_hz, width_divisor):.3f} Hz"
    )
    spectra.set_title(
        f"{channel_name}: CMB through the 4 f_HWP notch ({notch}; measured on "
        f"{100 * fsky:.0f}% of sky)"
    )
    spectra.legend(fontsize=7, ncol=2)
    ratio.semilogx(ell[keep], table["transfer_ee"][keep], color="tab:blue", label="EE -> EE")
    ratio.semilogx(ell[keep], table["transfer_bb"][keep], color="tab:red", label="BB -> BB")
    ratio.axhline(1.0, color="gray", lw=0.8)
    ratio.set_ylim(0, 1.2)
    ratio.set_xlabel(r"multipole $\ell$")
    ratio.set_ylabel(r"$F_\ell$ = $C_\ell$(notch) / $C_\ell$(no notch)")
    ratio.legend(fontsize=8)
    for ax in (spectra, ratio):
        ax.grid(alpha=0.3)
    save_figure(fig, path)
