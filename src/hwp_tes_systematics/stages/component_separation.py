"""Stage: harmonic ILC over all channels for one seed and each case, and the CMB residual.

For each case ``nosys`` or ``sigma<value>`` the residual of :class:`ilc_residuals.SeedMaps`
(the paper's HILC, weights recomputed on the contaminated maps) and its foreground part
are written as a_lm, with the weights and the mask, one file per case; the systematic's
spectra through the no-systematics weights (the systematic-only estimator) go to a CSV,
and so do, for each fixed instrument (:func:`systematics.instrument_g1_draws`), its
systematic's BB and cross spectrum with the no-systematics residual. Each channel's a_lm
are computed (or read, on the map-domain path) once for all of them.
"""

from __future__ import annotations

import json
import logging

import h5py
import numpy as np

from ..analysis.ilc_residuals import SeedMaps
from ..analysis.systematics import NOSYS, sigma_of_case
from ..io import atomic_path, write_csv
from ..sky import map_metadata

log = logging.getLogger(__name__)


def run(
    config: dict,
    seed: int,
    cases: list[str],
    map_paths: dict[str, str],
    out_h5s: list[str],
    systematic_csv: str,
    mask_path: str | None = None,
    instruments_csv: str | None = None,
    fixed_instruments: int = 0,
    template_fit_json: str | None = None,
) -> None:
    """HILC of (seed, case) for each case, written to ``out_h5s[i]`` for ``cases[i]``; the
    systematic-only spectra (sigma_g1 = 1, no-systematics weights) to ``systematic_csv``;
    the spectra of ``fixed_instruments`` fixed instruments to ``instruments_csv``.
    ``map_paths``: {channel: maps file}, or {channel: a_lm file} made on ``mask_path``;
    ``template_fit_json``: the template fit's report per systematics channel
    (mitigation.template_fit; an empty list when it is null)."""
    if len(cases) != len(out_h5s):
        raise ValueError(f"component_separation: {len(cases)} cases but {len(out_h5s)} outputs")
    if NOSYS not in cases:
        raise ValueError(f"component_separation: the cases {cases} lack {NOSYS!r}")
    seed_maps = SeedMaps.from_files(config, seed, map_paths, mask_path)
    nosys = None
    for case, out_h5 in zip(cases, out_h5s, strict=True):
        result = write_case(config, seed_maps, case, out_h5)
        if case == NOSYS:
            nosys = result
    write_csv(seed_maps.systematic_spectra(nosys["weights"], nosys["residual_alm"]), systematic_csv)
    log.info("seed %d: wrote the systematic-only spectra %s", seed, systematic_csv)
    if template_fit_json is not None:
        write_template_fits(seed_maps, template_fit_json)
    if instruments_csv is not None:
        instruments = [seed_maps.instrument_draws(index) for index in range(fixed_instruments)]
        table = seed_maps.instrument_spectra(nosys, instruments)
        write_csv(table, instruments_csv)
        log.info(
            "seed %d: %d fixed instruments, wrote %s", seed, fixed_instruments, instruments_csv
        )


def write_case(config: dict, seed_maps: SeedMaps, case: str, out_h5: str) -> dict:
    """The residual of one case (nosys or sigma<value>) of the loaded realization; returns it."""
    sigma = sigma_of_case(case, config["requirement"]["sigma_g1_per_k"])
    result = seed_maps.residual(sigma)
    with atomic_path(out_h5) as temporary, h5py.File(temporary, "w") as out:
        for name, values in result.items():
            out.create_dataset(name, data=values)
        out.create_dataset("bins", data=np.array(seed_maps.bins))
        out.create_dataset("mask", data=seed_maps.mask)
        out.attrs.update(
            {
                "seed": seed_maps.seed,
                "case": case,
                "sigma_g1_per_k": sigma,
                "lmax": seed_maps.lmax,
                "channels": seed_maps.names,
                "common_fwhm_arcmin": seed_maps.common_fwhm_arcmin,
                "units": "K_CMB",
                **map_metadata(seed_maps.common_fwhm_arcmin),
                **seed_maps.fractions,
            }
        )
    log.info(
        "seed %d %s: HILC of %d channels on %.1f%% of the sky (common FWHM %.1f')",
        seed_maps.seed,
        case,
        len(seed_maps.names),
        100 * seed_maps.fractions["fsky"],
        seed_maps.common_fwhm_arcmin,
    )
    return result


def write_template_fits(seed_maps: SeedMaps, out_json: str) -> None:
    """The template fit's report of every systematics channel (:meth:`ChannelAlms.template_fit`)."""
    reports = [
        {
            key: value.tolist() if isinstance(value, np.ndarray) else value
            for key, value in r.items()
        }
        for r in seed_maps.template_fits
    ]
    with atomic_path(out_json) as temporary:
        temporary.write_text(json.dumps({"seed": seed_maps.seed, "channels": reports}, indent=1))
    for r in seed_maps.template_fits:
        log.info(
            "seed %d %s: template fit (%s, rank %d): response to the injected draws %s, "
            "error %s 1/K",
            seed_maps.seed,
            r["channel"],
            r["basis"],
            r["rank"],
            np.round(
                r["fitted_unit_response"]
                / np.where(r["injected_unit_draw"] == 0, 1, r["injected_unit_draw"]),
                3,
            ),
            np.array2string(r["fit_error_per_k"], precision=2),
        )
