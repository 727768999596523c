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

import healpy as hp
import numpy as np
import pandas as pd

from . import config as cfg
from . import hilc, map_domain, spectra
from .maps_file import read_channel_maps
from .systematics import unit_g1_draws

N_TEMPLATE_TERMS = 3  # s^2, s h, h^2
SPECTRA = ("tt", "ee", "bb", "te", "eb", "tb")  # hp.alm2cl order


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


@dataclass
class SeedMaps:
    """The channel maps of one realization and everything the HILC needs to combine them."""

    config: dict
    seed: int
    names: list[str]
    channel_maps: list[dict] = field(repr=False)
    mask: np.ndarray = field(repr=False)
    fwhms_arcmin: list[float]
    common_fwhm_arcmin: float
    lmax: int
    bins: list[tuple[int, int]]
    fractions: dict
    unit_draws: list[np.ndarray]
    map2alm_iter: int = hilc.MAP2ALM_ITER
    _alms: dict = field(default_factory=dict, repr=False)  # kind -> a_lm, computed once

    @classmethod
    def load(cls, config: dict, seed: int, map_paths: dict[str, str]) -> SeedMaps:
        settings = config["component_separation"]
        names = list(map_paths)
        channel_maps = [read_channel_maps(map_paths[name]) for name in names]
        lmax = settings["lmax"] if settings["lmax"] is not None else 2 * config["maps"]["nside"]
        mask = analysis_mask(channel_maps, settings)
        fwhms = [cfg.channel(config, name).fwhm_arcmin for name in names]
        fractions = spectra.fsky_weights(mask)
        bins = hilc.merge_bins_for_modes(
            hilc.multipole_bins(settings["lmin"], lmax, settings["bin_width"]),
            fractions["fsky"],
            len(names),
            settings["min_modes_per_channel"],
        )
        systematics = set(config["instrument"]["systematics_channels"])
        per = config["requirement"]["g1_per"]
        draws = [
            unit_g1_draws(config["master_seed"], name, seed, data["attrs"]["detectors"], per)
            if name in systematics
            else np.zeros(len(data["attrs"]["detectors"]))
            for name, data in zip(names, channel_maps, strict=True)
        ]
        return cls(
            config=config,
            seed=seed,
            names=names,
            channel_maps=channel_maps,
            mask=mask,
            fwhms_arcmin=fwhms,
            common_fwhm_arcmin=settings["common_fwhm_arcmin"] or max(fwhms),
            lmax=lmax,
            bins=bins,
            fractions=fractions,
            unit_draws=draws,
            map2alm_iter=settings["map2alm_iter"],
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

    def reference_alms(self, kind: str) -> np.ndarray:
        """a_lm of the "cmb_reference" or "foreground_reference" maps (computed once)."""
        return self._cached_alms(
            kind, lambda data, draws, c: np.where(data["nosys"] == hp.UNSEEN, hp.UNSEEN, data[kind])
        )

    def input_cmb_alms(self) -> np.ndarray:
        """a_lm of the seed's input CMB, unfiltered, per channel: the draw of
        :func:`map_domain.band_limited_seed_cmb` (the one every path simulates) at the
        channel's beam, on the channel's observed pixels, masked and at the common beam
        like every other map (computed once)."""
        simulation = self.config["simulation"]

        def input_map(data, draws, c):
            nside = hp.npix2nside(data["nosys"].shape[-1])
            alm, band = map_domain.band_limited_seed_cmb(
                3 * nside - 1,
                simulation["cmb_r"],
                self.config["master_seed"],
                self.seed,
                self.fwhms_arcmin[c],
            )
            cmb = hp.alm2map(alm, nside, lmax=band, pixwin=False)
            return np.where(data["nosys"] == hp.UNSEEN, hp.UNSEEN, cmb)

        return self._cached_alms("cmb_input", input_map)

    def data_alms(self, sigma_g1_per_k: float) -> np.ndarray:
        """a_lm of m_nosys + sigma sum_k z_k T_k for every channel, by linearity of the
        masked, beam-matched transform: a(m_nosys) + sigma a(sum_k z_k T_k), both computed
        once per realization (equal to transforming each case's maps, to round-off)."""
        nosys = self._cached_alms("nosys", lambda data, draws, c: data["nosys"])
        if sigma_g1_per_k == 0.0:
            return nosys
        return nosys + sigma_g1_per_k * self._cached_alms("contamination", _contamination)

    def _cached_alms(self, kind: str, map_of) -> np.ndarray:
        """(n_channels, 3, nalm) a_lm of ``map_of(channel maps, g1 draws, channel index)``
        per channel, at the common beam (computed once; a channel whose ``map_of`` is None
        gets zeros)."""
        if kind not in self._alms:
            alms = np.zeros((len(self.names), 3, hp.Alm.getsize(self.lmax)), dtype=complex)
            for c, (data, draws) in enumerate(zip(self.channel_maps, self.unit_draws, strict=True)):
                maps = map_of(data, draws, c)
                if maps is not None:
                    alms[c] = self.alms_of_channel(c, maps)
            self._alms[kind] = alms
        return self._alms[kind]

    def alms_of_channel(self, c: int, maps: np.ndarray) -> np.ndarray:
        """(3, nalm) a_lm of one (3, npix) map of channel ``c``, masked, at the common beam."""
        return hilc.channel_alms(
            [maps],
            [self.fwhms_arcmin[c]],
            self.mask,
            self.lmax,
            self.common_fwhm_arcmin,
            self.map2alm_iter,
        )[0]

    def residual(self, sigma_g1_per_k: float) -> dict[str, np.ndarray]:
        """The paper's HILC at sigma: weights recomputed on the contaminated maps.

        Returns {"residual_alm", "foreground_residual_alm", "cmb_input_alm",
        "cmb_filter_loss_alm" (3, nalm), "weights" (3, n_bins, n_channels)}: the residual
        against the filtered CMB reference, its foreground part, the input CMB through the
        weights, and what the filters took from it (sum_c w_c (a_ref,c - a_in,c); the
        residual against the unfiltered input is residual_alm + cmb_filter_loss_alm)."""
        data = self.data_alms(sigma_g1_per_k)
        _, weights = hilc.harmonic_ilc(data, self.bins, self.lmax)
        cmb = self.reference_alms("cmb_reference")
        cmb_input = self.input_cmb_alms()
        foreground = self.reference_alms("foreground_reference")

        def combined(alms):
            return hilc.apply_ilc(alms, weights, self.bins, self.lmax)

        return {
            "residual_alm": combined(data - cmb),
            "foreground_residual_alm": combined(foreground),
            "cmb_input_alm": combined(cmb_input),
            "cmb_filter_loss_alm": combined(cmb - cmb_input),
            "weights": weights,
        }

    def systematic_term_alms(self, weights: np.ndarray) -> np.ndarray:
        """X_j (3 terms, 3 T/E/B, nalm) at sigma = 1 [K_CMB K]: the template terms of every
        channel, times c_j(A_c) = (1, 2 A_c, A_c^2) and the g1 draws, through ``weights``."""
        nalm = hp.Alm.getsize(self.lmax)
        terms = np.zeros((N_TEMPLATE_TERMS, len(self.names), 3, nalm), dtype=complex)
        for c, (data, draws) in enumerate(zip(self.channel_maps, self.unit_draws, strict=True)):
            if not np.any(draws):
                continue
            a2_k = float(data["attrs"]["a2_k_cmb"])
            seen = data["nosys"][0] != hp.UNSEEN
            for j, coefficient in enumerate((1.0, 2.0 * a2_k, a2_k**2)):
                contamination = np.full_like(data["nosys"], hp.UNSEEN)
                summed = np.tensordot(draws, data["template_terms"][j], axes=1)
                contamination[:, seen] = coefficient * summed[:, seen]
                terms[j, c] = self.alms_of_channel(c, contamination)
        return np.array([hilc.apply_ilc(t, weights, self.bins, self.lmax) for t in terms])

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
        )

    def systematic_spectra(self, nosys_weights: np.ndarray) -> pd.DataFrame:
        """:func:`systematic_spectra_table` through the no-systematics weights."""
        return systematic_spectra_table(
            self.systematic_term_alms(nosys_weights),
            self.lmax,
            self.fractions,
            self.common_fwhm_arcmin,
        )


def _contamination(data: dict, unit_draws: np.ndarray, channel_index: int) -> np.ndarray | None:
    """sum_k z_k T_k (3, npix) at sigma = 1 [K_CMB K], UNSEEN where the channel is
    unobserved; None for a channel without systematics (all z_k = 0)."""
    if not np.any(unit_draws):
        return None
    seen = data["nosys"][0] != hp.UNSEEN
    summed = np.tensordot(np.asarray(unit_draws, dtype=float), data["templates"], axes=1)
    return np.where(seen, summed, hp.UNSEEN)


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
) -> pd.DataFrame:
    """EE and BB [K_CMB^2] of the residual, its foreground part and the rest (noise), with
    the same normalisation (:func:`unit_beam_spectra`), and the mask's fsky_eff.

    With the input CMB through the weights and the filters' loss
    (:meth:`SeedMaps.residual`), also: ``residual_unfiltered_cmb`` (the residual against
    the unfiltered input CMB, the paper's words read literally), ``cmb_input`` (its
    spectrum) and ``cmb_recovered_x_input`` (the cross spectrum of the recovered CMB,
    input + loss, with the input): their ratio is the sky's end-to-end transfer T_ell."""
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
