"""One channel's a_lm of one realization, and the analysis mask they are taken on.

Per seed and channel the pieces of the map are kept apart as a_lm on the common mask at a
common beam (:class:`ChannelAlms`): the map without the systematic (``nosys``), the
references the residual is taken against, the systematic's template terms (the fixed
pass's, :func:`fixed_term_alms`, once per channel; the seed's own), and the optional
kinds the model measures (the CMB's B modes alone, the tensor probe, the leakage). They
are written per channel and seed (:func:`write_channel_alms`) and combined over channels
by the HILC in :class:`.ilc_residuals.SeedMaps`.
"""

from __future__ import annotations

from dataclasses import dataclass

import h5py
import healpy as hp
import numpy as np

from .. import config as cfg
from ..io import atomic_path
from ..simulation import fixed_maps, map_domain
from ..sky import cmb as sky_cmb
from ..sky import harmonics
from . import hilc, spectra, template_fit
from .systematics import unit_g1_draws

N_TEMPLATE_TERMS = 3  # s^2, s h, h^2
SPECTRA = ("tt", "ee", "bb", "te", "eb", "tb")  # hp.alm2cl order
# the a_lm a channel contributes to a realization's HILC (ChannelAlms), at the common beam
ALM_KINDS = ("nosys", "cmb_reference", "foreground_reference", "cmb_input")
# on the map-domain path, the part of cmb_reference that is the filters' leakage of T and E
# into B (map_domain.realize_seed); zero for a channel without it
LEAKAGE_KIND = "cmb_leakage"
# on the map-domain path, the seed's CMB B modes alone before and after the filters
# (map_domain.realize_seed): what an r scales; the rest of the recovered CMB is not
B_ONLY_KINDS = ("cmb_input_b", "cmb_reference_b")
# on the map-domain path, the seed's tensor probe (B modes alone at r = 1) before and after
# the filters (map_domain.realize_seed): the map's response to r
TENSOR_KINDS = ("tensor_input_b", "tensor_reference_b")
TERM_KINDS = tuple(f"x{j}" for j in range(N_TEMPLATE_TERMS))  # c_j(A) sum_k z_k T^j_k
# on the map-domain path, a seed's own part of the s h term X^1, in two pieces
PIECE_KINDS = tuple(f"x1_{piece}" for piece in map_domain.SH_TERM_PIECES)
TEMPLATE_PARTS = ("fixed", *map_domain.SH_TERM_PIECES)  # the template's split
# a map-domain channel's fixed-pass part of X^1 (a seed's X^1 is it plus the seed's pieces):
# given to ChannelAlms.from_maps with the other known a_lm, never stored
FIXED_SH_KIND = "x1_fixed"
# map-based template fitting (:mod:`template_fit`) of a channel at sigma_g1 = 1: what is left
# of its contamination, what the fit takes from its map without the systematic, and what
# it leaves of a g1 common to the channel's detectors (the common population)
FIT_KINDS = ("fit_residual", "fit_removed", "fit_common_residual")
FIT_RESIDUAL, FIT_REMOVED, FIT_COMMON_RESIDUAL = FIT_KINDS


def analysis_mask(observed: list[np.ndarray], settings: dict) -> np.ndarray:
    """Apodized common mask at the maps' resolution: observed in every channel
    (``observed``: one (npix,) bool or (3, npix) map per channel, UNSEEN where
    unobserved), |b| >= cut, the region decided on the ``analysis_nside`` grid (if set:
    the same region at every map-making resolution, :func:`spectra.common_mask`)."""
    maps = [np.where(o, 0.0, hp.UNSEEN) if o.dtype == bool else o for o in observed]
    binary = spectra.common_mask(
        maps, settings["galactic_cut_deg"], region_nside=settings.get("analysis_nside")
    )
    if binary.sum() == 0:
        raise ValueError(
            "the common mask is empty: no pixel is observed by every channel outside the "
            f"Galactic cut of {settings['galactic_cut_deg']} deg (simulate longer or lower "
            "component_separation.galactic_cut_deg)"
        )
    return spectra.apodized_mask(binary, settings["mask_apodization_deg"])


@dataclass(frozen=True)
class HarmonicSettings:
    """What every channel's a_lm share: the band, the common beam, the map2alm iterations."""

    lmax: int
    common_fwhm_arcmin: float
    map2alm_iter: int

    @classmethod
    def from_config(cls, config: dict) -> HarmonicSettings:
        settings = config["component_separation"]
        fwhms = [cfg.channel(config, name).fwhm_arcmin for name in cfg.selected_channels(config)]
        return cls(
            lmax=cfg.analysis_lmax(config),
            common_fwhm_arcmin=settings["common_fwhm_arcmin"] or max(fwhms),
            map2alm_iter=settings["map2alm_iter"],
        )

    def alm(self, maps: np.ndarray, fwhm_arcmin: float, mask: np.ndarray) -> np.ndarray:
        """(3, nalm) a_lm of one (3, npix) map, masked, brought to the common beam."""
        return hilc.channel_alms(
            [maps], [fwhm_arcmin], mask, self.lmax, self.common_fwhm_arcmin, self.map2alm_iter
        )[0]


@dataclass
class ChannelAlms:
    """One channel's share of a realization's HILC, as a_lm (3, nalm) at the common beam
    on the common mask: ``alms`` holds ALM_KINDS (the no-systematics map, the CMB and
    foreground references through the filters, the unfiltered input CMB) and, on a
    systematics channel, TERM_KINDS per detector, (n_det, 3, nalm): c_j(A_2) T^j_k with
    c = (1, 2 A_2, A_2^2), so that for any unit g1 draws z_k the channel's contamination
    is sum_j X^j with X^j = sum_k z_k c_j T^j_k (:meth:`term`). The draws are the
    analysis' choice, not the maps': ``unit_draws`` are the seed's own, and a fixed
    instrument (:func:`systematics.instrument_g1_draws`) combines the same a_lm. Made
    from a maps file (:meth:`from_maps`), or from a seed's maps in memory and stored
    (:func:`write_channel_alms`): the map-domain path never writes a seed's maps."""

    name: str
    alms: dict[str, np.ndarray]
    detectors: list[str]
    a2_k_cmb: float
    unit_draws: np.ndarray

    @classmethod
    def from_maps(
        cls,
        config: dict,
        seed: int,
        name: str,
        data: dict,
        mask: np.ndarray,
        harmonic: HarmonicSettings,
        known: dict[str, np.ndarray] | None = None,
    ) -> ChannelAlms:
        """From a channel's maps (:func:`maps_file.read_channel_maps` layout: nosys,
        template_terms, cmb_reference, foreground_reference, attrs; and cmb_input, the
        seed's unfiltered CMB map, if the maps were made in memory: otherwise drawn again).
        ``known``: a_lm already computed for this channel's maps (e.g. the
        foreground_reference, the same for every seed of a fixed pass), used as given.
        Maps without ``template_terms`` (a map-domain seed made with ``full_terms=False``)
        take X^0, X^2 and the fixed part of X^1 from ``known`` (:func:`fixed_term_alms`)
        and add the seed's pieces to X^1: the a_lm are linear in the maps."""
        fwhm = cfg.channel(config, name).fwhm_arcmin
        detectors = [str(d) for d in data["attrs"]["detectors"]]
        a2_k = float(data["attrs"]["a2_k_cmb"])
        draws = channel_g1_draws(config, name, seed, detectors)
        unseen = data["nosys"] == hp.UNSEEN
        known = known or {}
        alms = {kind: alm for kind, alm in known.items() if kind != FIXED_SH_KIND}
        alms["nosys"] = harmonic.alm(data["nosys"], fwhm, mask)
        for kind in ("cmb_reference", "foreground_reference"):
            if kind not in alms:
                alms[kind] = harmonic.alm(np.where(unseen, hp.UNSEEN, data[kind]), fwhm, mask)
        cmb_input = data.get("cmb_input")
        if cmb_input is None:
            cmb_input = _input_cmb_map(config, seed, fwhm, unseen.shape[-1])
        alms["cmb_input"] = harmonic.alm(np.where(unseen, hp.UNSEEN, cmb_input), fwhm, mask)
        for kind in (LEAKAGE_KIND, *B_ONLY_KINDS, *TENSOR_KINDS):
            if kind in data:
                alms[kind] = harmonic.alm(np.where(unseen, hp.UNSEEN, data[kind]), fwhm, mask)
        if np.any(draws):
            seen = ~unseen[0]
            pieces = data.get("sh_term_pieces", {})
            for piece, kind in zip(map_domain.SH_TERM_PIECES, PIECE_KINDS, strict=True):
                if piece in pieces:
                    alms[kind] = _term_alms(pieces[piece], 2.0 * a2_k, seen, fwhm, mask, harmonic)
            if "template_terms" in data:
                coefficients = _term_coefficients(a2_k)
                for terms, coefficient, kind in zip(
                    data["template_terms"], coefficients, TERM_KINDS, strict=True
                ):
                    alms[kind] = _term_alms(terms, coefficient, seen, fwhm, mask, harmonic)
            else:
                needed = (*TERM_KINDS[::2], FIXED_SH_KIND, *PIECE_KINDS)
                missing = [kind for kind in needed if kind not in known and kind not in alms]
                if missing:
                    raise ValueError(
                        f"{name} seed {seed}: maps without template_terms need the fixed "
                        f"pass's term a_lm and the seed's pieces; missing {missing}"
                    )
                alms[TERM_KINDS[1]] = known[FIXED_SH_KIND] + sum(alms[k] for k in PIECE_KINDS)
        return cls(name, alms, detectors, a2_k, draws)

    def term(self, kind: str, draws=None) -> np.ndarray:
        """The a_lm (3, nalm) of ``kind``: one of ALM_KINDS as stored, or of TERM_KINDS
        X^j = sum_k z_k c_j T^j_k for the unit draws ``draws`` (the seed's own by
        default); zeros for a term of a channel without systematics."""
        if kind not in self.alms:
            return np.zeros_like(self.alms["nosys"])
        if kind not in (*TERM_KINDS, *PIECE_KINDS):
            return self.alms[kind]
        draws = self.unit_draws if draws is None else np.asarray(draws, dtype=float)
        return np.tensordot(draws, self.alms[kind], axes=1)

    def detector_templates(self) -> np.ndarray:
        """(n_det, 3, nalm) each detector's whole contamination at g1 = 1 1/K, sum_j c_j
        T^j_k [K_CMB K]; zeros for a channel without systematics."""
        if TERM_KINDS[0] not in self.alms:
            return np.zeros((len(self.detectors), *self.alms["nosys"].shape), complex)
        return sum(self.alms[kind] for kind in TERM_KINDS)

    def known_terms(self) -> list[np.ndarray]:
        """[c_j T^j_k (n_det, 3, nalm) for j = 0, 1, 2]: what a template fit knows of each
        detector's terms, the whole of them less the seed's own CMB and noise through the
        s h term (the map-domain path's pieces; the TOD path has none, so its templates
        are known whole)."""
        known = [self.alms[kind] for kind in TERM_KINDS]
        pieces = [self.alms[kind] for kind in PIECE_KINDS if kind in self.alms]
        if pieces:
            known[1] = known[1] - sum(pieces)
        return known

    def template_fit(self, basis: str, lmax: int) -> tuple[dict[str, np.ndarray], dict]:
        """({kind: (3, nalm)} for FIT_KINDS, report) of :class:`template_fit.TemplateFit`
        of the known templates (:meth:`known_terms`, ``basis``) on this channel:
        fit_residual = X - P X, X the contamination at sigma_g1 = 1 1/K with the seed's
        draws; fit_removed = P m, m the map without the systematic; fit_common_residual =
        X_c - P X_c, X_c = sum_k K_k the contamination of g1 = 1 1/K on every detector;
        report: per basis row the injected unit draw, the fitted coefficient of X (its
        response, 1 x the draw for a known template), the coefficient of m (the fit's
        error at any sigma_g1 [1/K]) and the formal error."""
        terms = self.known_terms()
        fit = template_fit.TemplateFit.build(
            template_fit.channel_basis(terms, basis),
            template_fit.inverse_spectrum_weights(self.alms["nosys"], lmax),
        )
        contamination = sum(self.term(kind) for kind in TERM_KINDS)
        nosys = self.alms["nosys"]
        rows = (
            self.detectors
            if basis == "detector"
            else [f"{d}:{t}" for t in ("s2", "sh", "h2") for d in self.detectors]
        )
        report = {
            "channel": self.name,
            "basis": basis,
            "templates_known": "the fixed pass's (a seed's own CMB x h and noise x h unknown)"
            if any(kind in self.alms for kind in PIECE_KINDS)
            else "whole (TOD path: the seed's own CMB and noise in them; what no instrument "
            "knows, an upper bound on the fit)",
            "rank": fit.rank,
            "rows": rows,
            "injected_unit_draw": np.tile(self.unit_draws, len(rows) // len(self.detectors)),
            "fitted_unit_response": fit.coefficients(contamination),
            "fit_error_per_k": fit.coefficients(nosys),
            "formal_error_per_k": fit.coefficient_errors(),
        }
        common = self.detector_templates().sum(axis=0)
        left = {
            FIT_RESIDUAL: contamination - fit.fitted(contamination),
            FIT_REMOVED: fit.fitted(nosys),
            FIT_COMMON_RESIDUAL: common - fit.fitted(common),
        }
        return left, report


def _term_coefficients(a2_k: float) -> tuple[float, float, float]:
    """c_j(A_2) = (1, 2 A_2, A_2^2) of the terms s^2, s h, h^2 [K^0, K, K^2]."""
    return 1.0, 2.0 * a2_k, a2_k**2


def _term_alms(templates, coefficient, seen, fwhm_arcmin, mask, harmonic) -> np.ndarray:
    """(n_det, 3, nalm) a_lm of coefficient x each detector's (3, npix) template, UNSEEN
    off ``seen``, at the common beam on ``mask``."""
    alms = []
    for template in templates:
        term = np.full(template.shape, hp.UNSEEN)
        term[:, seen] = coefficient * template[:, seen]
        alms.append(harmonic.alm(term, fwhm_arcmin, mask))
    return np.array(alms)


def fixed_term_alms(
    config: dict, name: str, fixed: fixed_maps.FixedMaps, a2_k: float, mask, harmonic
) -> dict[str, np.ndarray]:
    """The a_lm of a map-domain channel's template terms that every seed shares, once per
    channel: X^0 and X^2 per detector (a seed keeps the fixed pass's s^2 and h^2 terms)
    and FIXED_SH_KIND, the fixed pass's part of X^1 ({} for a channel without
    systematics). Given to :meth:`ChannelAlms.from_maps` as ``known`` with a seed's maps
    made without their terms, it saves six transforms per seed of an MFT/HFT pair."""
    if not fixed.carries_systematics:
        return {}
    fwhm = cfg.channel(config, name).fwhm_arcmin
    coefficients = _term_coefficients(a2_k)
    kinds = (TERM_KINDS[0], FIXED_SH_KIND, TERM_KINDS[2])
    return {
        kind: _term_alms(fixed.template_terms[j], coefficients[j], fixed.good, fwhm, mask, harmonic)
        for j, kind in enumerate(kinds)
    }


def channel_g1_draws(
    config: dict, name: str, seed: int, detectors: list[str], draw=unit_g1_draws
) -> np.ndarray:
    """The unit g1 draws z_k of a channel's detectors (zeros outside the systematics
    channels): the seed's own (``draw`` = :func:`systematics.unit_g1_draws`), or with
    :func:`systematics.instrument_g1_draws` and ``seed`` the instrument's number; times
    :func:`emulated_template_scale` for a focal plane emulated by the seeds."""
    if name not in config["instrument"]["systematics_channels"]:
        return np.zeros(len(detectors))
    per = config["requirement"]["g1_per"]
    draws = np.asarray(draw(config["master_seed"], name, seed, detectors, per), float)
    return draws * emulated_template_scale(config, name)


def emulated_template_scale(config: dict, name: str) -> float:
    """sqrt(N / N_e) (:func:`config.emulated_pairs_factor`): a g1 on N simulated detectors
    whose template power is that of N_e pairs' (1 when the seeds emulate nothing)."""
    return float(np.sqrt(cfg.emulated_pairs_factor(config, name)))


def _input_cmb_map(config: dict, seed: int, fwhm_arcmin: float, npix: int) -> np.ndarray:
    """(3, npix) the seed's unfiltered CMB at a channel's beam: the draw of
    :func:`sky.cmb.band_limited_seed_cmb` (the one every path simulates)."""
    nside = hp.npix2nside(npix)
    alm, band = sky_cmb.band_limited_seed_cmb(
        3 * nside - 1, config["simulation"]["cmb_r"], config["master_seed"], seed, fwhm_arcmin
    )
    return harmonics.alm2map(alm, nside, band)


def write_channel_alms(path, channel: ChannelAlms, attributes: dict) -> None:
    """One channel's :class:`ChannelAlms` of one seed as HDF5 (``alm_<kind>`` datasets)."""
    with atomic_path(path) as temporary, h5py.File(temporary, "w") as out:
        for kind, alm in channel.alms.items():
            out.create_dataset(f"alm_{kind}", data=alm)
        out.create_dataset("unit_draws", data=channel.unit_draws)
        out.attrs.update(attributes)
        out.attrs.update(
            {"channel": channel.name, "detectors": channel.detectors, "a2_k_cmb": channel.a2_k_cmb}
        )


def read_channel_alms(path, harmonic: HarmonicSettings, mask_sum: float) -> ChannelAlms:
    """A file of :func:`write_channel_alms`, checked against the analysis it joins."""
    with h5py.File(path) as stored:
        attributes = dict(stored.attrs)
        alms = {name[4:]: stored[name][()] for name in stored if name.startswith("alm_")}
        draws = stored["unit_draws"][()]
    for kind in (*TERM_KINDS, *PIECE_KINDS):
        if kind in alms and alms[kind].ndim != 3:
            raise ValueError(
                f"{path}: alm_{kind} has shape {alms[kind].shape}, expected one a_lm per "
                "detector (n_det, 3, nalm): made by an older map_domain_alms (rerun it)"
            )
    expected = {
        "lmax": harmonic.lmax,
        "common_fwhm_arcmin": harmonic.common_fwhm_arcmin,
        "map2alm_iter": harmonic.map2alm_iter,
        "mask_sum": mask_sum,
    }
    for key, value in expected.items():
        if key not in attributes or not np.isclose(attributes[key], value, rtol=1e-12):
            raise ValueError(
                f"{path}: made with {key} = {attributes.get(key)}, the analysis has {value} "
                "(rerun its map_domain_alms rule)"
            )
    detectors = [str(d) for d in attributes["detectors"]]
    return ChannelAlms(
        str(attributes["channel"]), alms, detectors, float(attributes["a2_k_cmb"]), draws
    )


def alms_attributes(seed: int, harmonic: HarmonicSettings, mask: np.ndarray) -> dict:
    """What a channel a_lm file records of the analysis it was made for."""
    return {
        "seed": seed,
        "lmax": harmonic.lmax,
        "common_fwhm_arcmin": harmonic.common_fwhm_arcmin,
        "map2alm_iter": harmonic.map2alm_iter,
        "mask_sum": float(mask.sum()),
        "units": "K_CMB",
    }


def write_mask(path, mask: np.ndarray, settings: dict) -> None:
    """The analysis mask (npix,) as HDF5, with the settings that made it."""
    with atomic_path(path) as temporary, h5py.File(temporary, "w") as out:
        out.create_dataset("mask", data=mask)
        out.attrs.update(
            {key: settings[key] for key in ("galactic_cut_deg", "mask_apodization_deg")}
        )
        out.attrs["analysis_nside"] = settings.get("analysis_nside") or hp.npix2nside(mask.size)


def read_mask(path) -> np.ndarray:
    with h5py.File(path) as stored:
        return stored["mask"][()]
