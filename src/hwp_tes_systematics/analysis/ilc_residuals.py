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

import numpy as np
import pandas as pd

from .. import config as cfg
from ..simulation import map_domain
from ..simulation.maps_file import read_channel_maps
from . import hilc, spectra
from .channel_alms import (
    ALM_KINDS,
    B_ONLY_KINDS,
    FIT_COMMON_RESIDUAL,
    FIT_KINDS,
    FIT_REMOVED,
    FIT_RESIDUAL,
    LEAKAGE_KIND,
    N_TEMPLATE_TERMS,
    PIECE_KINDS,
    SPECTRA,
    TEMPLATE_PARTS,
    TENSOR_KINDS,
    TERM_KINDS,
    ChannelAlms,
    HarmonicSettings,
    analysis_mask,
    channel_g1_draws,
    emulated_template_scale,
    read_channel_alms,
    read_mask,
)
from .systematics import instrument_g1_draws


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
            for kind in FIT_KINDS:
                channel_alms[kind] = np.array(
                    [
                        np.zeros_like(c.alms["nosys"]) if f is None else f[0][kind]
                        for c, f in zip(channels, fits, strict=True)
                    ]
                )
            template_fits = [f[1] for f in fits if f is not None]
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
            channel_g1_draws(self.config, name, instrument, detectors, instrument_g1_draws)
            for name, detectors in zip(self.names, self.detectors, strict=True)
        ]

    def common_offset_draws(self) -> list[np.ndarray]:
        """g1 = 1 1/K on every detector of the systematics channels (a residual common to
        the focal plane, :func:`fixed_instruments.common_offset_estimator`), zeros on the
        others: the draws of an instrument with no spread (times
        :func:`channel_alms.emulated_template_scale` for an emulated focal plane)."""
        systematic = self.config["instrument"]["systematics_channels"]
        return [
            np.full(
                len(detectors),
                emulated_template_scale(self.config, name) if name in systematic else 0.0,
            )
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
        [K_CMB^2 K]): at sigma, C_obs = C_nosys + 2 sigma C_cross + sigma^2 C_auto; the
        same of the common offset (:meth:`common_offset_draws`), ``..._common_offset_...``;
        with the template fit, the same of what the fit leaves of the common offset
        (FIT_KINDS' fit_common_residual) against the residual that lost the fit's P m,
        ``..._common_offset_mitigated_...``."""
        weights = nosys["weights"]
        residuals = {
            "cross": nosys["residual_alm"],
            "cross_unfiltered": nosys["residual_alm"] + nosys["cmb_filter_loss_alm"],
        }
        entries = [
            (f"instrument{index}", self.instrument_template_alms(draws, weights), residuals)
            for index, draws in enumerate(instruments)
        ]
        entries.append(
            (
                "common_offset",
                self.instrument_template_alms(self.common_offset_draws(), weights),
                residuals,
            )
        )
        if FIT_COMMON_RESIDUAL in self.channel_alms:
            left, removed = (
                hilc.apply_ilc(self.channel_alms[kind], weights, self.bins, self.lmax)
                for kind in (FIT_COMMON_RESIDUAL, FIT_REMOVED)
            )
            mitigated = {label: alm - removed for label, alm in residuals.items()}
            entries.append(("common_offset_mitigated", left, mitigated))
        table = {"ell": np.arange(self.lmax + 1)}
        for name, template, against in entries:
            for label, alm2 in (("auto", None), *against.items()):
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
        if nosys_residual_alm is not None and FIT_RESIDUAL in self.channel_alms:
            residual, removed = (
                hilc.apply_ilc(self.channel_alms[kind], nosys_weights, self.bins, self.lmax)
                for kind in (FIT_RESIDUAL, FIT_REMOVED)
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
