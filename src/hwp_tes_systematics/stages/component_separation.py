"""Stage: harmonic ILC over all channels for one (seed, case), and the CMB residual.

For realization ``seed`` and case ``nosys`` or ``sigma<value>``, every channel's map is
m_c = m_nosys,c + sigma sum_k z_ck T_ck (only the systematics channels carry g1). On a
common mask (pixels observed by every channel, outside a Galactic cut, apodized) the
a_lm of each channel are brought to a common beam and combined by the HILC
(w = C^-1 e / e^T C^-1 e per multipole bin, T, E, B separately). The residual is

    r_lm = sum_c w_c (a_c - a_ref,c),

with a_ref,c the input CMB of channel c through the same pointing, filter and binning,
so that the notch's action on the CMB does not appear as a residual. The same weights
applied to the foreground references give the foreground residual; the rest is the
noise (+ dipole and HWPSS leakage) residual.
"""

from __future__ import annotations

import logging

import h5py
import healpy as hp
import numpy as np

from .. import config as cfg
from .. import hilc, spectra
from ..io import atomic_path
from ..systematics import maps_for_sigma, sigma_of_case, unit_g1_draws

log = logging.getLogger(__name__)


def read_channel_maps(path) -> dict:
    with h5py.File(path) as maps:
        data = {name: maps[name][()] for name in maps}
        data["attrs"] = dict(maps.attrs)
    return data


def analysis_mask(channel_maps: list[dict], settings: dict) -> np.ndarray:
    """Apodized common mask: observed in every channel, |b| >= cut."""
    binary = spectra.common_mask([m["nosys"] for m in channel_maps], settings["galactic_cut_deg"])
    if binary.sum() == 0:
        raise ValueError(
            "the common mask is empty: no pixel is observed by every channel outside the "
            f"Galactic cut of {settings['galactic_cut_deg']} deg (simulate longer or lower "
            "component_separation.galactic_cut_deg)"
        )
    return spectra.apodized_mask(binary, settings["mask_apodization_deg"])


def run(config: dict, seed: int, case: str, map_paths: dict[str, str], out_h5: str) -> None:
    """HILC of (seed, case); writes the residual and foreground-residual a_lm and weights."""
    settings = config["component_separation"]
    sigma = sigma_of_case(case, config["requirement"]["sigma_g1_per_k"])
    names = list(map_paths)
    channel_maps = [read_channel_maps(map_paths[name]) for name in names]
    nside = config["maps"]["nside"]
    lmax = settings["lmax"] if settings["lmax"] is not None else 2 * nside
    mask = analysis_mask(channel_maps, settings)
    fwhms = [cfg.channel(config, name).fwhm_arcmin for name in names]
    common_fwhm = settings["common_fwhm_arcmin"] or max(fwhms)
    systematics = set(config["instrument"]["systematics_channels"])

    def alms_of(kind: str) -> np.ndarray:
        maps = []
        for name, data in zip(names, channel_maps, strict=True):
            if kind == "data":
                draws = unit_g1_draws(config["master_seed"], name, seed, data["attrs"]["detectors"])
                maps.append(
                    maps_for_sigma(
                        data["nosys"],
                        data["templates"],
                        draws,
                        sigma if name in systematics else 0.0,
                    )
                )
            else:
                maps.append(np.where(data["nosys"] == hp.UNSEEN, hp.UNSEEN, data[kind]))
        return hilc.channel_alms(maps, fwhms, mask, lmax, common_fwhm)

    data_alms = alms_of("data")
    cmb_alms = alms_of("cmb_reference")
    foreground_alms = alms_of("foreground_reference")
    fractions = spectra.fsky_weights(mask)
    bins = hilc.merge_bins_for_modes(
        hilc.multipole_bins(settings["lmin"], lmax, settings["bin_width"]),
        fractions["fsky"],
        len(names),
        settings["min_modes_per_channel"],
    )
    _, weights = hilc.harmonic_ilc(data_alms, bins, lmax)
    residual = hilc.apply_ilc(data_alms - cmb_alms, weights, bins, lmax)
    foreground_residual = hilc.apply_ilc(foreground_alms, weights, bins, lmax)
    with atomic_path(out_h5) as temporary, h5py.File(temporary, "w") as out:
        out.create_dataset("residual_alm", data=residual)
        out.create_dataset("foreground_residual_alm", data=foreground_residual)
        out.create_dataset("weights", data=weights)
        out.create_dataset("bins", data=np.array(bins))
        out.create_dataset("mask", data=mask)
        out.attrs.update(
            {
                "seed": seed,
                "case": case,
                "sigma_g1_per_k": sigma,
                "lmax": lmax,
                "channels": names,
                "common_fwhm_arcmin": common_fwhm,
                "units": "K_CMB",
                **fractions,
            }
        )
    log.info(
        "seed %d %s: HILC of %d channels on %.1f%% of the sky (common FWHM %.1f')",
        seed,
        case,
        len(names),
        100 * fractions["fsky"],
        common_fwhm,
    )
