"""Stage: what the 4 f_HWP notch does to the sky's polarisation (input CMB spectra).

The notch removes any signal within ~2 delta f of 4 f_HWP, including sky
polarisation whose TOD frequency 4 f_HWP +- f_scan(ell) falls there: with the
PTEP scan speed (f_scan ~ ell x 6e-4 Hz) and delta f = 0.026 Hz (MFT), the
multipoles below ~50-100. Sys and nosys maps pass the same filter.
"""

from __future__ import annotations

import logging

import healpy as hp
import numpy as np
import pandas as pd

from .. import config as cfg
from .. import seeding, sky
from ..figures.tod import plot_notch_effect
from ..io import write_csv
from ..simulation.mapmaking import NormalEquations, solve_maps
from ..simulation.notch import chunk_span
from ..simulation.tod import PairSimulator
from ..simulation.tod_filter import filter_tod
from ..simulation.tod_maps import PairMapSettings, detector_weights

log = logging.getLogger(__name__)


def pure_mode_sky(nside: int, lmax: int, mode: str, fwhm_arcmin: float, master_seed: int):
    """A white-spectrum (C_ell = 1 K^2) polarised sky with only E or only B modes, beamed."""
    cls = np.zeros((4, lmax + 1))
    cls[{"E": 1, "B": 2}[mode], 2:] = 1.0
    alm = sky.gaussian_alm(cls, lmax, seeding.rng(master_seed, "notch_effect", mode))
    alm = sky.smooth_alm(alm, fwhm_arcmin, lmax)
    return hp.alm2map(alm, nside, lmax=lmax, pixwin=False)


def notch_transfer_on_sky(config: dict, channel_name: str) -> pd.DataFrame:
    """EE -> EE and BB -> BB transfer of the notch, and the input CMB spectra through it.

    Noise-free TODs of an E-only and a B-only sky (white spectra) are binned with and
    without the notch on the same samples; F_XX(ell) = C_ell(notch) / C_ell(no notch)
    on the observed pixels. Pure-mode skies avoid the mask's E -> B leakage.
    """
    channel = cfg.channel(config, channel_name)
    settings = PairMapSettings.from_config(config, channel, seed=0, a2_k_cmb=0.0)
    settings.removed_hwp_harmonics = ()  # the notch alone
    simulator = PairSimulator.from_config(config, channel, settings.plan, settings.nside)
    lmax = 3 * settings.nside - 1
    skies = [
        pure_mode_sky(settings.nside, lmax, mode, channel.fwhm_arcmin, config["master_seed"])
        for mode in ("E", "B")
    ]
    equations = NormalEquations(settings.nside, 4)
    for _, first, n_samples in settings.plan.chunks():
        start, n_simulated, inner = chunk_span(
            first, n_samples, settings.plan.sampling_rate_hz, settings.notch_margin_s
        )
        pointing = simulator.pointing(start, n_simulated)
        tods = []
        for sky_map in skies:
            tod = simulator.scan_sky(pointing, sky_map)
            tods += [filter_tod(tod, pointing, inner, simulator, settings), tod[:, inner]]
        equations.add(
            pointing.pixels[:, inner],
            pointing.cos_2alpha[:, inner],
            pointing.sin_2alpha[:, inner],
            detector_weights(simulator),
            simulator.pol_efficiency,
            tods,
        )
    maps, _, good = solve_maps(equations, settings.max_condition_number)
    fsky = good.mean()

    def spectrum(iqu, index):
        return hp.anafast(np.where(good, iqu, 0.0), lmax=lmax)[index] / fsky

    transfer_ee = spectrum(maps[0], 1) / spectrum(maps[1], 1)
    transfer_bb = spectrum(maps[2], 2) / spectrum(maps[3], 2)
    ell = np.arange(lmax + 1)
    lensing = sky.cmb_spectra(config["simulation"]["cmb_r"], lmax)
    tensor_bb = sky.tensor_bb_r1(lmax)
    table = pd.DataFrame(
        {
            "ell": ell,
            "transfer_ee": transfer_ee,
            "transfer_bb": transfer_bb,
            "cmb_ee_k2": lensing[1],
            "cmb_bb_k2": lensing[2],
            "tensor_bb_r1_k2": tensor_bb,
        }
    )
    table["observed_fraction"] = fsky
    log.info("%s: notch transfer measured on %.1f%% of the sky", channel_name, 100 * fsky)
    return table


def run(config: dict, channel_name: str, out_csv: str, out_png: str) -> None:
    table = notch_transfer_on_sky(config, channel_name)
    write_csv(table, out_csv)
    f_hwp_hz = cfg.channel(config, channel_name).hwp_frequency_hz
    plot_notch_effect(table, channel_name, f_hwp_hz, config["notch"]["width_divisor"], out_png)
