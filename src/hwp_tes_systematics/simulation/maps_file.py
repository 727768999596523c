"""The per-(channel, seed) maps file: what the TOD path and the map-domain path write and
the component separation reads (HDF5, RING, Galactic).

Datasets: nosys (3, npix) [K_CMB]; template_terms (3, n_det, 3, npix) [K_CMB^2], the binned
s^2, s h, h^2 of each detector (h: unit HWPSS); templates (n_det, 3, npix) [K_CMB^2] =
their sum at the file's A_2; cmb_reference and foreground_reference (3, npix) [K_CMB]
(each sky component alone through the same pointing, filter and binning); hits and
condition (npix). Attributes: units, POLCCONV, FWHM, FREQ, channel, seed, detectors,
A_2, noise scale, baseline length, duration, observed fraction and the model in words.
"""

from __future__ import annotations

import h5py
import numpy as np

from .. import sky
from ..io import atomic_path
from .tod_maps import TEMPLATE_TERMS

MODEL = (
    "m(g1) = nosys + sum_k g1_k templates[k]; g1 in 1/K; templates[k] = "
    "template_terms[0, k] + 2 A_2 template_terms[1, k] + A_2^2 template_terms[2, k]"
)


def maps_attributes(settings, simulator, observed_fraction: float) -> dict:
    """The attributes of a maps file simulated with ``settings`` and ``simulator``."""
    return {
        "units": "K_CMB",
        "template_units": "K_CMB^2 (templates, template_terms; times g1 [1/K]: K_CMB)",
        **sky.map_metadata(simulator.channel.fwhm_arcmin, simulator.channel.bandcenter_ghz),
        "coordinates": "Galactic",
        "ordering": "RING",
        "nside": settings.nside,
        "channel": simulator.channel.name,
        "seed": settings.seed,
        "detectors": simulator.detector_names,
        "pol_angles_rad": simulator.pol_angles_rad,
        "a2_k_cmb": settings.a2_k_cmb,
        "noise_scale": settings.noise_scale,
        "baseline_length_s": np.nan
        if settings.baseline_length_s is None
        else settings.baseline_length_s,
        "template_terms": list(TEMPLATE_TERMS),
        "duration_s": settings.plan.duration_s,
        "chunk_stride": settings.plan.chunk_stride,  # every n-th chunk of duration_s simulated
        "observed_fraction": float(observed_fraction),
        "model": MODEL,
    }


def write_channel_maps(path, maps: dict, hits, condition, attributes: dict) -> None:
    """Write ``maps`` (nosys, templates, template_terms, cmb_reference,
    foreground_reference), hits and condition with ``attributes``, atomically."""
    with atomic_path(path) as temporary, h5py.File(temporary, "w") as out:
        for name in (
            "nosys",
            "templates",
            "template_terms",
            "cmb_reference",
            "foreground_reference",
        ):
            out.create_dataset(name, data=maps[name])
        out.create_dataset("hits", data=hits)
        out.create_dataset("condition", data=condition)
        out.attrs.update(attributes)


def read_channel_maps(path, names=None) -> dict:
    """The datasets ``names`` (default: all) of a maps file, and its attributes under
    "attrs"."""
    with h5py.File(path) as maps:
        data = {name: maps[name][()] for name in (maps if names is None else names)}
        data["attrs"] = dict(maps.attrs)
    return data
