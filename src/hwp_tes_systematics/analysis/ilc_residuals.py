"""The HILC CMB residual of one realization at any sigma_g1, and the systematic alone.

For realization ``seed`` every channel's map is m_c = m_nosys,c + sigma sum_k z_ck T_ck
(only the systematics channels carry g1; :mod:`systematics`). On a common mask (pixels
observed by every channel, outside a Galactic cut, apodized) the a_lm of each channel
are brought to a common beam and combined by the HILC (:mod:`hilc`). Two residuals:

* the paper's: weights w(sigma) recomputed on the contaminated maps, residual
  r_lm = sum_c w_c (a_c - a_ref,c), with a_ref,c the input CMB of channel c through the
  same pointing, filter and binning (so the notch's action on the CMB cancels);
* the systematic alone: the weights of the no-systematics case applied to the
  contamination only, s_lm = sigma sum_c w_c^nosys sum_k z_ck T_ck, whose spectrum is
  exactly sigma^2 times that of sigma = 1 (no cross term with noise or foregrounds, no
  re-weighting);
* the paper's words read literally (``likelihood.model: paper_literal``): the residual
  against the *unfiltered* input CMB, r_lm + sum_c w_c (a_ref,c - a_in,c), with a_in,c
  the seed's CMB at channel c's beam before any filter (:meth:`SeedMaps.input_cmb_alms`):
  it keeps the part of the CMB that the notch removed. The same a_lm give the end-to-end
  transfer of the sky, T_ell = C(sum w a_ref, sum w a_in) / C(sum w a_in).

With the template split T = T_ss + 2 A_2 T_sh + A_2^2 T_hh
  (:mod:`stages.pair_maps`) and A_2 scaled by a on every channel,
  s_lm(a) = X0 + a X1 + a^2 X2, X_j = sum_c w_c sum_k z_ck c_j(A_c) T^j_ck with
  c = (1, 2 A_c, A_c^2): three a_lm give the systematic for every HWPSS amplitude.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import h5py
import healpy as hp
import numpy as np
import pandas as pd

from .. import config as cfg
from ..io import atomic_path
from ..simulation import fixed_maps, map_domain
from ..simulation.maps_file import read_channel_maps
from ..sky import cmb as sky_cmb
from ..sky import harmonics
from . import hilc, spectra, template_fit
from .systematics import instrument_g1_draws, unit_g1_draws

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
# of its contamination, and what the fit takes from its map without the systematic
FIT_KINDS = ("fit_residual", "fit_removed")


def analysis_mask(observed: list[np.ndarray], settings: dict) -> np.ndarray:
    """Apodized common mask: observed in every channel (``observed``: one (npix,) bool or
    (3, npix) map per channel, UNSEEN where unobserved), |b| >= cut."""
    maps = [np.where(o, 0.0, hp.UNSEEN) if o.dtype == bool else o for o in observed]
    binary = spectra.common_mask(maps, settings["galactic_cut_deg"])
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
        lmax = settings["lmax"] if settings["lmax"] is not None else 2 * config["maps"]["nside"]
        return cls(
            lmax=lmax,
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
        draws = _unit_draws(config, name, seed, detectors)
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

    def template_fit(self, basis: str, lmax: int) -> tuple[np.ndarray, np.ndarray, dict]:
        """(residual, removed, report) of :class:`template_fit.TemplateFit` of the known
        templates (:meth:`known_terms`, ``basis``) on this channel with the seed's draws:
        residual = X - P X, X the contamination at sigma_g1 = 1 1/K; removed = P m, m the
        map without the systematic (both (3, nalm)); report: per basis row the injected
        unit draw, the fitted coefficient of X (its response, 1 x the draw for a known
        template), the coefficient of m (the fit's error at any sigma_g1 [1/K]) and the
        formal error."""
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
        return contamination - fit.fitted(contamination), fit.fitted(nosys), report


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


def _unit_draws(
    config: dict, name: str, seed: int, detectors: list[str], draw=unit_g1_draws
) -> np.ndarray:
    """The unit g1 draws z_k of a channel's detectors (zeros outside the systematics
    channels): the seed's own (``draw`` = :func:`systematics.unit_g1_draws`), or with
    :func:`systematics.instrument_g1_draws` and ``seed`` the instrument's number."""
    if name not in config["instrument"]["systematics_channels"]:
        return np.zeros(len(detectors))
    per = config["requirement"]["g1_per"]
    return np.asarray(draw(config["master_seed"], name, seed, detectors, per), float)


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


def read_mask(path) -> np.ndarray:
    with h5py.File(path) as stored:
        return stored["mask"][()]


@dataclass
class SeedMaps:
    """Every channel's a_lm of one realization (:class:`ChannelAlms`) and everything the
    HILC needs to combine them."""

    config: dict
    seed: int
    names: list[str]
    mask: np.ndarray = field(repr=False)
    fwhms_arcmin: list[float]
    common_fwhm_arcmin: float
    lmax: int
    bins: list[tuple[int, int]]
    fractions: dict
    unit_draws: list[np.ndarray]
    channel_alms: dict[str, np.ndarray] = field(repr=False)  # kind -> (n_ch, 3, nalm)
    # per channel (n_det, 3, nalm): each detector's contamination at g1 = 1 1/K
    detector_templates: list[np.ndarray] = field(repr=False, default_factory=list)
    detectors: list[list[str]] = field(default_factory=list)  # per channel
    map2alm_iter: int = hilc.MAP2ALM_ITER
    # per systematics channel: ChannelAlms.template_fit's report (mitigation.template_fit)
    template_fits: list[dict] = field(default_factory=list)

    @classmethod
    def load(cls, config: dict, seed: int, map_paths: dict[str, str]) -> SeedMaps:
        """From the channels' maps files (the TOD path's pair_maps): the mask from every
        channel's observed pixels, then each channel's a_lm (one channel's maps in
        memory at a time)."""
        observed = [
            ~hilc.unseen_pixels(read_channel_maps(path, ("nosys",))["nosys"])
            for path in map_paths.values()
        ]
        mask = analysis_mask(observed, config["component_separation"])
        harmonic = HarmonicSettings.from_config(config)
        channels = [
            ChannelAlms.from_maps(config, seed, name, read_channel_maps(path), mask, harmonic)
            for name, path in map_paths.items()
        ]
        return cls.combine(config, seed, channels, mask, harmonic)

    @classmethod
    def from_alm_files(
        cls, config: dict, seed: int, alm_paths: dict[str, str], mask_path: str
    ) -> SeedMaps:
        """From the channels' a_lm files (the map-domain path's map_domain_alms) and the
        analysis mask they were made on."""
        mask = read_mask(mask_path)
        harmonic = HarmonicSettings.from_config(config)
        channels = [read_channel_alms(p, harmonic, float(mask.sum())) for p in alm_paths.values()]
        for name, channel in zip(alm_paths, channels, strict=True):
            if channel.name != name:
                raise ValueError(f"{alm_paths[name]}: holds channel {channel.name}, not {name}")
        return cls.combine(config, seed, channels, mask, harmonic)

    @classmethod
    def from_files(cls, config: dict, seed: int, paths: dict[str, str], mask_path=None):
        """:meth:`from_alm_files` with a mask, :meth:`load` (maps files) without."""
        if mask_path is None:
            return cls.load(config, seed, paths)
        return cls.from_alm_files(config, seed, paths, mask_path)

    @classmethod
    def combine(cls, config, seed, channels: list[ChannelAlms], mask, harmonic) -> SeedMaps:
        settings = config["component_separation"]
        fractions = spectra.fsky_weights(mask)
        bins = hilc.merge_bins_for_modes(
            hilc.multipole_bins(settings["lmin"], harmonic.lmax, settings["bin_width"]),
            fractions["fsky"],
            len(channels),
            settings["min_modes_per_channel"],
        )
        kinds = (*ALM_KINDS, *TERM_KINDS)
        if any(kind in c.alms for c in channels for kind in PIECE_KINDS):
            kinds = (*kinds, *PIECE_KINDS)
        if any(LEAKAGE_KIND in c.alms for c in channels):
            kinds = (*kinds, LEAKAGE_KIND)
        for optional in (B_ONLY_KINDS, TENSOR_KINDS):
            if all(kind in c.alms for c in channels for kind in optional):
                kinds = (*kinds, *optional)
        channel_alms = {kind: np.array([c.term(kind) for c in channels]) for kind in kinds}
        basis = config.get("mitigation", {}).get("template_fit")
        template_fits = []
        if basis is not None:
            fits = [
                c.template_fit(basis, harmonic.lmax) if TERM_KINDS[0] in c.alms else None
                for c in channels
            ]
            for i, kind in enumerate(FIT_KINDS):
                channel_alms[kind] = np.array(
                    [
                        np.zeros_like(c.alms["nosys"]) if f is None else f[i]
                        for c, f in zip(channels, fits, strict=True)
                    ]
                )
            template_fits = [f[2] for f in fits if f is not None]
        return cls(
            config=config,
            seed=seed,
            names=[c.name for c in channels],
            mask=mask,
            fwhms_arcmin=[cfg.channel(config, c.name).fwhm_arcmin for c in channels],
            common_fwhm_arcmin=harmonic.common_fwhm_arcmin,
            lmax=harmonic.lmax,
            bins=bins,
            fractions=fractions,
            unit_draws=[c.unit_draws for c in channels],
            channel_alms=channel_alms,
            detector_templates=[c.detector_templates() for c in channels],
            detectors=[c.detectors for c in channels],
            map2alm_iter=harmonic.map2alm_iter,
            template_fits=template_fits,
        )

    def alms(self, maps: list[np.ndarray]) -> np.ndarray:
        """(n_channels, 3, nalm) a_lm of one map per channel, masked, at the common beam."""
        return hilc.channel_alms(
            maps,
            self.fwhms_arcmin,
            self.mask,
            self.lmax,
            self.common_fwhm_arcmin,
            self.map2alm_iter,
        )

    def data_alms(self, sigma_g1_per_k: float) -> np.ndarray:
        """a_lm of m_nosys + sigma sum_k z_k T_k for every channel, by linearity of the
        masked, beam-matched transform: a(m_nosys) + sigma sum_j X^j (equal to
        transforming each case's maps, to round-off)."""
        nosys = self.channel_alms["nosys"]
        if sigma_g1_per_k == 0.0:
            return nosys
        contamination = sum(self.channel_alms[kind] for kind in TERM_KINDS)
        return nosys + sigma_g1_per_k * contamination

    def residual(self, sigma_g1_per_k: float) -> dict[str, np.ndarray]:
        """The paper's HILC at sigma: weights recomputed on the contaminated maps.

        Returns {"residual_alm", "foreground_residual_alm", "cmb_input_alm",
        "cmb_filter_loss_alm" (3, nalm), "weights" (3, n_bins, n_channels)}: the residual
        against the filtered CMB reference, its foreground part, the input CMB through the
        weights, and what the filters took from it (sum_c w_c (a_ref,c - a_in,c); the
        residual against the unfiltered input is residual_alm + cmb_filter_loss_alm); on
        the map-domain path also "cmb_leakage_alm", the filters' T and E leakage into B
        through the weights (a part of the recovered CMB), and "cmb_input_b_alm",
        "cmb_recovered_b_only_alm", the input CMB's B modes alone through the weights
        before and after the filters; with the seed's tensor probe, "tensor_input_b_alm"
        and "tensor_recovered_b_alm", the same for B modes alone at r = 1."""
        data = self.data_alms(sigma_g1_per_k)
        _, weights = hilc.harmonic_ilc(data, self.bins, self.lmax)
        cmb = self.channel_alms["cmb_reference"]
        cmb_input = self.channel_alms["cmb_input"]
        foreground = self.channel_alms["foreground_reference"]

        def combined(alms):
            return hilc.apply_ilc(alms, weights, self.bins, self.lmax)

        result = {
            "residual_alm": combined(data - cmb),
            "foreground_residual_alm": combined(foreground),
            "cmb_input_alm": combined(cmb_input),
            "cmb_filter_loss_alm": combined(cmb - cmb_input),
            "weights": weights,
        }
        if LEAKAGE_KIND in self.channel_alms:
            result["cmb_leakage_alm"] = combined(self.channel_alms[LEAKAGE_KIND])
        if all(kind in self.channel_alms for kind in B_ONLY_KINDS):
            result["cmb_input_b_alm"] = combined(self.channel_alms["cmb_input_b"])
            result["cmb_recovered_b_only_alm"] = combined(self.channel_alms["cmb_reference_b"])
        if all(kind in self.channel_alms for kind in TENSOR_KINDS):
            result["tensor_input_b_alm"] = combined(self.channel_alms["tensor_input_b"])
            result["tensor_recovered_b_alm"] = combined(self.channel_alms["tensor_reference_b"])
        return result

    def systematic_term_alms(self, weights: np.ndarray) -> np.ndarray:
        """X_j (3 terms, 3 T/E/B, nalm) at sigma = 1 [K_CMB K]: the template terms of every
        channel, times c_j(A_c) = (1, 2 A_c, A_c^2) and the g1 draws, through ``weights``."""
        return np.array(
            [
                hilc.apply_ilc(self.channel_alms[kind], weights, self.bins, self.lmax)
                for kind in TERM_KINDS
            ]
        )

    def instrument_draws(self, instrument: int) -> list[np.ndarray]:
        """The unit g1 draws of fixed instrument ``instrument``, one array per channel
        (zeros on the channels without systematics)."""
        return [
            _unit_draws(self.config, name, instrument, detectors, instrument_g1_draws)
            for name, detectors in zip(self.names, self.detectors, strict=True)
        ]

    def common_offset_draws(self) -> list[np.ndarray]:
        """g1 = 1 1/K on every detector of the systematics channels (a residual common to
        the focal plane, :func:`fixed_instruments.common_offset_estimator`), zeros on the
        others: the draws of an instrument with no spread."""
        systematic = self.config["instrument"]["systematics_channels"]
        return [
            np.full(len(detectors), 1.0 if name in systematic else 0.0)
            for name, detectors in zip(self.names, self.detectors, strict=True)
        ]

    def instrument_template_alms(self, draws: list[np.ndarray], weights: np.ndarray):
        """(3, nalm) the systematic at sigma_g1 = 1 1/K of one instrument [K_CMB K]: the
        unit draws ``draws`` (one array per channel, :func:`systematics.instrument_g1_draws`)
        on every detector's template, combined through ``weights``."""
        contamination = np.array(
            [
                np.tensordot(np.asarray(z, dtype=float), templates, axes=1)
                for z, templates in zip(draws, self.detector_templates, strict=True)
            ]
        )
        return hilc.apply_ilc(contamination, weights, self.bins, self.lmax)

    def instrument_spectra(
        self, nosys: dict[str, np.ndarray], instruments: list[list[np.ndarray]]
    ) -> pd.DataFrame:
        """For fixed instruments (each a list of per-channel unit draws), the BB of the
        systematic at sigma_g1 = 1 1/K through the no-systematics weights
        (``bb_auto_instrument<i>_k4`` [K_CMB^2 K^2]) and its cross spectra with the
        no-systematics residual ``nosys`` (:meth:`residual` at sigma 0) against the
        filtered CMB reference and against the unfiltered input
        (``bb_cross_instrument<i>_k3``, ``bb_cross_unfiltered_instrument<i>_k3``
        [K_CMB^2 K]): at sigma, C_obs = C_nosys + 2 sigma C_cross + sigma^2 C_auto; and
        the same of the common offset (:meth:`common_offset_draws`), ``..._common_offset_...``."""
        residuals = {
            "cross": nosys["residual_alm"],
            "cross_unfiltered": nosys["residual_alm"] + nosys["cmb_filter_loss_alm"],
        }
        table = {"ell": np.arange(self.lmax + 1)}
        named = [(f"instrument{index}", draws) for index, draws in enumerate(instruments)]
        for name, draws in [*named, ("common_offset", self.common_offset_draws())]:
            template = self.instrument_template_alms(draws, nosys["weights"])
            for label, alm2 in (("auto", None), *residuals.items()):
                cl = unit_beam_spectra(
                    template, alm2, self.lmax, self.fractions["w2"], self.common_fwhm_arcmin
                )
                unit = "k4" if label == "auto" else "k3"
                table[f"bb_{label}_{name}_{unit}"] = cl[2]
        out = pd.DataFrame(table)
        out["fsky_eff"] = self.fractions["fsky_eff"]
        return out

    def residual_spectra(self, sigma_g1_per_k: float) -> pd.DataFrame:
        """:func:`residual_spectra_table` of the paper's residual at sigma."""
        result = self.residual(sigma_g1_per_k)
        return residual_spectra_table(
            result["residual_alm"],
            result["foreground_residual_alm"],
            self.lmax,
            self.fractions,
            self.common_fwhm_arcmin,
            cmb_input_alm=result["cmb_input_alm"],
            cmb_filter_loss_alm=result["cmb_filter_loss_alm"],
            cmb_leakage_alm=result.get("cmb_leakage_alm"),
            cmb_input_b_alm=result.get("cmb_input_b_alm"),
            cmb_recovered_b_only_alm=result.get("cmb_recovered_b_only_alm"),
            tensor_input_b_alm=result.get("tensor_input_b_alm"),
            tensor_recovered_b_alm=result.get("tensor_recovered_b_alm"),
        )

    def systematic_spectra(
        self, nosys_weights: np.ndarray, nosys_residual_alm: np.ndarray | None = None
    ) -> pd.DataFrame:
        """:func:`systematic_spectra_table` through the no-systematics weights; on the
        map-domain path also the template's split (:meth:`template_split_alms`): BB
        ``bb_<a>_x_<b>_k4`` [K_CMB^2 K^2] of its parts a, b in TEMPLATE_PARTS. With the
        template fit (FIT_KINDS) and the no-systematics residual ``nosys_residual_alm``:
        ``bb_mitigated_k4``, the BB of what the fit leaves of the systematic at sigma_g1 =
        1 1/K; ``bb_fit_removed_k2``, that of what it takes from the map without the
        systematic, and ``bb_fit_removed_x_residual_k2``, its cross spectrum with the
        residual (the mitigated residual's BB is C_res - 2 C_x + C_removed + sigma^2
        C_mitigated + cross terms of zero mean)."""
        table = systematic_spectra_table(
            self.systematic_term_alms(nosys_weights),
            self.lmax,
            self.fractions,
            self.common_fwhm_arcmin,
        )
        if nosys_residual_alm is not None and FIT_KINDS[0] in self.channel_alms:
            residual, removed = (
                hilc.apply_ilc(self.channel_alms[kind], nosys_weights, self.bins, self.lmax)
                for kind in FIT_KINDS
            )
            for label, alm, alm2 in (
                ("mitigated_k4", residual, None),
                ("fit_removed_k2", removed, None),
                ("fit_removed_x_residual_k2", removed, nosys_residual_alm),
            ):
                cl = unit_beam_spectra(
                    alm, alm2, self.lmax, self.fractions["w2"], self.common_fwhm_arcmin
                )
                table[f"bb_{label}"] = cl[2]
        if PIECE_KINDS[0] not in self.channel_alms:
            return table
        parts = self.template_split_alms(nosys_weights)
        for i, a in enumerate(TEMPLATE_PARTS):
            for b in TEMPLATE_PARTS[i:]:
                cl = unit_beam_spectra(
                    parts[a],
                    None if a == b else parts[b],
                    self.lmax,
                    self.fractions["w2"],
                    self.common_fwhm_arcmin,
                )
                table[f"bb_{a}_x_{b}_k4"] = cl[2]
        return table

    def template_split_alms(self, weights: np.ndarray) -> dict[str, np.ndarray]:
        """The systematic at sigma_g1 = 1 1/K through ``weights`` in its TEMPLATE_PARTS
        (3, nalm) [K_CMB K]: ``fixed`` (the fixed pass's: the seed-independent sky s_f
        through the s h term, s^2 and h^2), ``cmb_h`` and ``noise_h`` (the seed's CMB and
        noise through the s h term); they sum to the whole."""
        total = self.systematic_term_alms(weights).sum(axis=0)
        parts = {
            piece: hilc.apply_ilc(self.channel_alms[kind], weights, self.bins, self.lmax)
            for piece, kind in zip(map_domain.SH_TERM_PIECES, PIECE_KINDS, strict=True)
        }
        return {"fixed": total - sum(parts.values()), **parts}


def unit_beam_spectra(alm, alm2, lmax: int, w2: float, common_fwhm_arcmin: float) -> np.ndarray:
    """(6, lmax + 1) pseudo-spectra / w2 of masked a_lm at the common beam, beam deconvolved
    (:func:`spectra.deconvolve_beam`): one normalisation for every residual spectrum."""
    return spectra.deconvolve_beam(spectra.pseudo_spectra(alm, lmax, w2, alm2), common_fwhm_arcmin)


def residual_spectra_table(
    residual_alm,
    foreground_residual_alm,
    lmax: int,
    fractions: dict,
    common_fwhm_arcmin: float,
    cmb_input_alm=None,
    cmb_filter_loss_alm=None,
    cmb_leakage_alm=None,
    cmb_input_b_alm=None,
    cmb_recovered_b_only_alm=None,
    tensor_input_b_alm=None,
    tensor_recovered_b_alm=None,
) -> pd.DataFrame:
    """EE and BB [K_CMB^2] of the residual, its foreground part and the rest (noise), with
    the same normalisation (:func:`unit_beam_spectra`), and the mask's fsky_eff.

    With the input CMB through the weights and the filters' loss
    (:meth:`SeedMaps.residual`), also: ``residual_unfiltered_cmb`` (the residual against
    the unfiltered input CMB, the paper's words read literally), ``cmb_input`` (its
    spectrum), ``cmb_recovered_x_input`` (the cross spectrum of the recovered CMB,
    input + loss, with the input: their ratio is the sky's end-to-end transfer T_ell),
    ``cmb_recovered`` (the recovered CMB's own spectrum) and ``recovered`` (the spectrum
    of the HILC's CMB map itself, recovered CMB + residual: what an experiment measures,
    on which an injected r is recovered, :func:`consistency.check_r_recovery`). With
    the filters' leakage through the weights (the map-domain path), also
    ``cmb_leakage`` (its spectrum) and ``cmb_recovered_b`` (the recovered CMB less it);
    with the input's B modes alone before and after the filters, ``cmb_input_b`` and
    ``cmb_recovered_b_only`` (their spectra: the power of the sky's B modes, which an r
    scales, the mask's E-to-B leakage apart); with the tensor probe (B modes alone at
    r = 1) before and after the filters, ``tensor_input_b`` and ``tensor_recovered_b``
    (the map's response to r, over C_GW^{r=1})."""
    table = {"ell": np.arange(lmax + 1)}
    pairs = [
        ("residual", residual_alm, None),
        ("foreground_residual", foreground_residual_alm, None),
        ("noise_residual", residual_alm - foreground_residual_alm, None),
    ]
    if cmb_input_alm is not None and cmb_filter_loss_alm is not None:
        pairs += [
            ("residual_unfiltered_cmb", residual_alm + cmb_filter_loss_alm, None),
            ("cmb_input", cmb_input_alm, None),
            ("cmb_recovered_x_input", cmb_input_alm + cmb_filter_loss_alm, cmb_input_alm),
            ("cmb_recovered", cmb_input_alm + cmb_filter_loss_alm, None),
            ("recovered", residual_alm + cmb_input_alm + cmb_filter_loss_alm, None),
        ]
        if cmb_leakage_alm is not None:
            recovered_b = cmb_input_alm + cmb_filter_loss_alm - cmb_leakage_alm
            pairs += [
                ("cmb_leakage", cmb_leakage_alm, None),
                ("cmb_recovered_b", recovered_b, None),
            ]
        if cmb_input_b_alm is not None and cmb_recovered_b_only_alm is not None:
            pairs += [
                ("cmb_input_b", cmb_input_b_alm, None),
                ("cmb_recovered_b_only", cmb_recovered_b_only_alm, None),
            ]
        if tensor_input_b_alm is not None and tensor_recovered_b_alm is not None:
            pairs += [
                ("tensor_input_b", tensor_input_b_alm, None),
                ("tensor_recovered_b", tensor_recovered_b_alm, None),
            ]
    for label, alm, alm2 in pairs:
        cl = unit_beam_spectra(alm, alm2, lmax, fractions["w2"], common_fwhm_arcmin)
        for index in (1, 2):
            table[f"{SPECTRA[index]}_{label}_k2"] = cl[index]
    out = pd.DataFrame(table)
    out["fsky_eff"] = fractions["fsky_eff"]
    return out


def systematic_spectra_table(
    term_alms, lmax: int, fractions: dict, common_fwhm_arcmin: float
) -> pd.DataFrame:
    """EE and BB cross spectra C[X_i, X_j] (i <= j) [K_CMB^2 K^2] of the systematic's terms
    (:meth:`SeedMaps.systematic_term_alms`), columns ``bb_x0x1_k4`` etc., and their sum
    at a = 1, ``bb_unit_k4``; the same normalisation as the residual spectra."""
    table = {"ell": np.arange(lmax + 1)}
    total = 0.0
    for i in range(N_TEMPLATE_TERMS):
        for j in range(i, N_TEMPLATE_TERMS):
            cl = unit_beam_spectra(
                term_alms[i], term_alms[j], lmax, fractions["w2"], common_fwhm_arcmin
            )
            for index in (1, 2):
                table[f"{SPECTRA[index]}_x{i}x{j}_k4"] = cl[index]
            total = total + (1 if i == j else 2) * cl
    for index in (1, 2):
        table[f"{SPECTRA[index]}_unit_k4"] = total[index]
    out = pd.DataFrame(table)
    out["fsky_eff"] = fractions["fsky_eff"]
    return out


def systematic_bb(table, a2_scale: float = 1.0) -> np.ndarray:
    """BB of the systematic alone at sigma_g1 = 1 and A_2 x ``a2_scale`` [K_CMB^2 K^2]:
    sum_ij a^(i+j) C[X_i, X_j] from a table of the cross spectra ``bb_x{i}x{j}_k4``
    (i <= j; :func:`systematic_spectra_table`)."""
    total = 0.0
    for i in range(N_TEMPLATE_TERMS):
        for j in range(i, N_TEMPLATE_TERMS):
            multiplicity = 1 if i == j else 2
            total = total + multiplicity * a2_scale ** (i + j) * table[f"bb_x{i}x{j}_k4"].to_numpy()
    return total
