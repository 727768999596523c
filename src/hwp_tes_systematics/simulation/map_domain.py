"""Realizations in the map domain: one seed-independent TOD pass per channel, then each
seed as map products (the fast path to one year; the full-TOD path stays the reference).

Of the TOD d = s + A_2 h, s = fg + dipole + CMB_seed + n_seed, only the CMB draw and the
noise depend on the seed. Writing s = s_f + x (s_f = fg + dipole, x = CMB_seed + n_seed),
the fixed pass simulates once, without CMB or noise, through the same HWP-harmonic
removal, notch, baselines and binning as the full path (:func:`tod_maps.accumulate`):

* m_f = bin F(s_f + A_2 h), the foreground reference bin F(fg), the template terms of s_f
  (s_f^2, s_f h, h^2 per detector);
* the HWPSS moments per detector k and pixel p (:class:`mapmaking.PixelMoments`):
  M_k = sum w a^T a, H_k = sum w h a^T a, Q_k = sum w h^2 a^T a (M = sum_k M_k);
* the filter's action on a reference CMB realization, T_ell = C_ell(bin F CMB, CMB) /
  C_ell(CMB) (TT, EE, BB), and on ``simulation.noise_reference_realizations`` reference
  noise realizations, the shaping S_ell (~ sqrt(sum C_ell(bin F n) / sum C_ell(bin n)),
  calibrated so that shaping bin n gives the pseudo-spectrum of bin F n on the observed
  pixels), and the shaping S^h_ell of the same noise times the unit HWPSS, h n (the s h
  term's noise: the filter does not act on h n as on n), each an expectation that one
  realization measures poorly at low ell (docs/physics/map_domain.md: with one
  realization and S_ell for both, H3-402's one-month seed part came out 17 % high, with
  four and S^h 10 %); all from every
  ``simulation.calibration_every_chunks``-th chunk (1 by default: a subset of the days
  biases the low-ell shaping, benchmarks/calibration_stride_validation.py).

Each seed then costs map operations only:

    nosys            = m_f + T CMB_seed + X_seed + S M^-1 sum_k b_k
    s h term of k    = (s_f h term of k) + T^h M^-1 H_k CMB_seed + S^h M^-1 c_k
    cmb_reference    = T CMB_seed + X_seed

and, for a demodulated map-maker only, the s^2 term of k gets the seed's 2 s_f CMB_seed
as detector k's share of S^s P(s_f, CMB_seed) (:func:`static_sky_product`,
:func:`demodulated_shares`; S^s, a shaping as S, measured in the pass: a transfer T^s
of cross spectra gave 48-76 % of the full path's B power at 30 days, as the filter's
E-to-B mixing is no transfer; benchmarks/s2_seed_part_validation.py),

with X_seed the BB the filter adds beyond T (mode mixing: T is a cross spectrum, and a
filter that mixes modes leaves more than T^2 of the power), two Gaussian B fields with
the excess the pass measured against the reference CMB by origin, its B modes and its
T and E modes (:func:`filter_response.measure_excess_bb`; the latter, the filter's
leakage into B, also kept alone as ``cmb_leakage``: the likelihood's tensor response is
the rest), drawn from streams common to the channels (:func:`sky.cmb.filter_excess_unit_alms`),
with (b_k, c_k) ~ N(0, noise_scale^2 [[M_k, H_k], [H_k, Q_k]]) the binned white noise and
binned h n of detector k, drawn jointly per pixel (exact for white noise: b_k = sum w a^T n,
c_k = sum w a^T h n, var(n) = 1 / w), T^h = 1 for the binned map-maker (the filter's
action on h CMB is left out, below) and, for HWP demodulation (``demodulated_variants``
of :func:`fixed_passes`), measured in the pass: the demodulated h x reference CMB against
M^-1 sum_k H_k of it, ~0 on a band-limited sky (h CMB sits at 2 f_HWP, which
demodulation moves to 2 and 6 f_HWP and its low-pass removes; a nearest-pixel scan's
steps put sky power there: ``simulation.sky_scanning``), and T, S, T^h applied to the
T, E, B a_lm up to
``simulation.filter_lmax`` (the map's whole band by default; the analysis reads nothing
above component_separation lmax, so at nside 512 stopping there saves most transforms).
What the seeds of a channel share (noise factors, M^-1, H_k) is computed once
(:class:`SeedOperators`). The binning
reads a TOD at 0 and 4 f_HWP, where the notch removes the noise's (and h n's) sky-scale
part: without S the map-domain noise is too high (by 2x in variance at 1 day, nside 32).
As the residual subtracts cmb_reference, the CMB cancels there exactly and enters only
through the HILC weights, as in the full path.

Approximated, and measured against the full path (tests/simulation/test_map_domain.py,
benchmarks/map_domain_validation.py): the filter as multipole functions (an
along-scan filter; good on a large observed sky, poor on a few hours' stripe); white
noise (the 1/f part is left out: it reaches I, not Q/U, with a HWP); the filter's
action on h CMB (7-13 % of that part); for the binned map-maker, the seed part of the
s^2 term, 2 s_f x + x^2 (2 % of the s h part: s_f is the dipole and foregrounds, mK,
against A_2 = 0.16-3.8 K; demodulation removes the s h part's sky and keeps it).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import h5py
import healpy as hp
import numpy as np

from .. import config as cfg
from .. import seeding
from ..sky import cmb as sky_cmb
from ..sky import harmonics
from .filter_response import (
    b_modes_alone,
    excess_bb_alms,
    filtered_cmb_map,
    shaped_noise_map,
    transferred_map,
)
from .fixed_maps import (
    BinnedNoise,
    FixedMaps,
    demodulated_shares,
    read_fixed_attribute,
    read_fixed_maps,
    static_sky_product,
)
from .tod_maps import TEMPLATE_TERMS, templates_from_terms

log = logging.getLogger(__name__)

SH_TERM = TEMPLATE_TERMS.index("s*h")
SH_TERM_PIECES = ("cmb_h", "noise_h")  # a seed's own part of the s h term


class SeedOperators:
    """What every seed of a channel applies, computed once from its fixed pass: the binned
    noise's factors (:class:`BinnedNoise`), M^-1 and the H_k of the good pixels, and the
    last multipole ``filter_lmax`` to which the filter's action (T_ell on the CMB, S_ell on
    the noise) is applied: the analysis reads no higher (component_separation lmax), and
    filtering beyond it costs transforms at the map's full band for nothing it uses."""

    def __init__(self, fixed: FixedMaps, noise_scale: float, filter_lmax: int):
        good = np.flatnonzero(fixed.good)
        self.noise = BinnedNoise(fixed, noise_scale)
        self.inverse = np.linalg.inv(fixed.matrices(good))  # (n_good, 3, 3) M^-1 [K^2]
        n_det = fixed.moments.shape[0] if fixed.carries_systematics else 0
        self.h_matrices = [fixed.moment(k, 1, good) for k in range(n_det)]  # H_k [K^-2]
        # (n_det, 3, n_good) the detectors' shares of a demodulated map [1], for the s^2
        # term's CMB part (if modelled)
        self.demodulated_shares = (
            demodulated_shares(fixed, good) if fixed.cmb_s_shaping.size else np.zeros(0)
        )
        self.filter_lmax = filter_lmax

    def solve(self, vectors: np.ndarray) -> np.ndarray:
        """M^-1 v on the good pixels: (3, n_good) -> (3, n_good)."""
        return np.einsum("pij,jp->ip", self.inverse, vectors)


def realize_seed(
    fixed: FixedMaps,
    cmb_alm: np.ndarray,
    lmax: int,
    a2_k_cmb: float,
    noise_scale: float,
    rng_of_detector,
    operators: SeedOperators | None = None,
    full_terms: bool = True,
    cmb_excess_alm: np.ndarray | None = None,
    tensor_alms: tuple[np.ndarray, np.ndarray] | None = None,
    map_noise_factor: float = 1.0,
) -> dict[str, np.ndarray]:
    """The maps of one seed from the fixed pass (see the module docstring): nosys,
    template_terms, templates, cmb_reference, foreground_reference (UNSEEN where the
    fixed pass is not good), as :func:`tod_maps.split_solved_maps` names them,
    cmb_input, the seed's CMB map before the filter (the map of ``cmb_alm``, everywhere),
    and the seed's two pieces of the s h term, ``sh_term_pieces`` {"cmb_h", "noise_h"}:
    (n_det, 3, npix) each, zero off the good pixels (the s h term is the fixed pass's
    plus these). Where the fixed pass measured S^s (a demodulated map-maker), "cmb_h"
    also carries the seed's CMB part of the s^2 term, detector k's share
    (:func:`demodulated_shares`) of S^s P(s_f, CMB) with P of
    :func:`static_sky_product`, divided by 2 A_2 (the s h term's coefficient in the
    template): the template is the same, and its seed part stays in two pieces.
    ``operators``: the :class:`SeedOperators` of (fixed, noise_scale), shared by the seeds
    of a channel (built here, filtering up to ``lmax``, if None). ``full_terms`` False
    leaves out template_terms and templates (the fixed pass's terms plus the pieces: the
    seeds' a_lm take the fixed part's once, :func:`..analysis.channel_alms.fixed_term_alms`).
    ``cmb_excess_alm``: (2, 3, nalm) the filters' excess BB of the seed by origin
    (:func:`filter_response.excess_bb_alms`, band ``operators.filter_lmax``), added to
    the filtered CMB; its second (T and E modes) also as ``cmb_leakage``; with it, also
    the seed's B modes alone before and after the filter, ``cmb_input_b`` and
    ``cmb_reference_b`` (T B + the excess of B origin: what the sky's B modes, and an r,
    put in the map; the rest of the recovered CMB is r-independent). ``tensor_alms``:
    (the seed's tensor probe, B modes alone at r = 1 (:func:`sky.cmb.tensor_b_alm`, band
    ``lmax``), its excess of B origin (band ``operators.filter_lmax``)), giving
    ``tensor_input_b`` and ``tensor_reference_b``, the probe before and after the filters:
    the map's response to r, which the lensing B modes cannot give where the filters and
    the mask mix multipoles (the spectra's shapes differ). ``map_noise_factor``: the
    binned white noise of nosys times it, sqrt(N / N_e) for a focal plane of N_e pairs
    emulated from the pass's N (:func:`config.emulated_pairs_factor`); a detector's own
    noise through the s h term keeps its size (its share of the map shrinks with the g1
    draws' scale instead)."""
    nside = hp.npix2nside(fixed.good.size)
    good = fixed.good
    operators = operators or SeedOperators(fixed, noise_scale, lmax)
    cmb = harmonics.alm2map(cmb_alm, nside, lmax)
    cmb_filtered = filtered_cmb_map(cmb, cmb_alm, fixed.transfer, lmax, operators.filter_lmax)
    leakage = None
    if cmb_excess_alm is not None:
        b_part, leakage = (
            harmonics.alm2map(alm, nside, operators.filter_lmax) for alm in cmb_excess_alm
        )
        cmb_filtered += b_part + leakage
    b, c = operators.noise.draw(rng_of_detector)

    def filtered_noise(vectors, shaping):  # the binned white noise, shaped by the filter
        white = np.zeros_like(fixed.nosys)
        white[:, good] = operators.solve(vectors)
        shaped = shaped_noise_map(white, shaping, good, operators.filter_lmax)
        return shaped[:, good]

    noise = np.zeros_like(fixed.nosys)
    noise[:, good] = map_noise_factor * filtered_noise(b[:, good], fixed.noise_shaping)
    nosys = np.full_like(fixed.nosys, hp.UNSEEN)
    nosys[:, good] = fixed.nosys[:, good] + cmb_filtered[:, good] + noise[:, good]
    pieces = {name: np.zeros_like(fixed.template_terms[SH_TERM]) for name in SH_TERM_PIECES}
    for k, h_k in enumerate(operators.h_matrices):  # the s h term gets the seed's part
        cmb_h = operators.solve(np.einsum("pij,jp->ip", h_k, cmb[:, good]))
        if fixed.cmb_h_transfer.size:  # a demodulated map-maker: as the fixed pass measured
            binned = np.zeros_like(fixed.nosys)
            binned[:, good] = cmb_h
            cmb_h = transferred_map(binned, fixed.cmb_h_transfer, good, operators.filter_lmax)
            cmb_h = cmb_h[:, good]
        pieces["cmb_h"][k][:, good] = cmb_h
        pieces["noise_h"][k][:, good] = filtered_noise(c[k][:, good], fixed.noise_h_shaping)
    if operators.demodulated_shares.size and a2_k_cmb:  # the s^2 term's CMB part, in s h units
        product = static_sky_product(fixed.static_sky, cmb)
        # shaped by S^s up to filter_lmax, kept as it is above (as the noise by S)
        product = shaped_noise_map(product, fixed.cmb_s_shaping, good, operators.filter_lmax)
        for k, share in enumerate(operators.demodulated_shares):
            pieces["cmb_h"][k][:, good] += share * product[:, good] / (2.0 * a2_k_cmb)
    maps = {
        "nosys": nosys,
        "cmb_reference": np.where(good, cmb_filtered, hp.UNSEEN),
        "foreground_reference": fixed.foreground_reference,
        "cmb_input": cmb,
        "sh_term_pieces": pieces,
    }

    def b_modes(alm, excess_map, prefix):  # B modes alone, before and after the filters
        unfiltered = harmonics.alm2map(alm, nside, lmax)
        filtered = filtered_cmb_map(unfiltered, alm, fixed.transfer, lmax, operators.filter_lmax)
        maps[f"{prefix}_input_b"] = unfiltered
        maps[f"{prefix}_reference_b"] = np.where(good, filtered + excess_map, hp.UNSEEN)

    if leakage is not None:
        maps["cmb_leakage"] = np.where(good, leakage, hp.UNSEEN)
        b_modes(b_modes_alone(cmb_alm), b_part, "cmb")
    if tensor_alms is not None:
        tensor_alm, tensor_excess = tensor_alms
        b_modes(
            tensor_alm, harmonics.alm2map(tensor_excess, nside, operators.filter_lmax), "tensor"
        )
    if full_terms:
        terms = fixed.template_terms.copy()
        terms[SH_TERM] += pieces["cmb_h"] + pieces["noise_h"]
        maps["template_terms"] = terms
        maps["templates"] = np.where(good, templates_from_terms(terms, a2_k_cmb), hp.UNSEEN)
    return maps


class ChannelSeeds:
    """The seeds of one channel made from its fixed pass file: :meth:`maps` of a seed as
    the TOD path's maps file holds them (nosys, template_terms, templates, cmb_reference,
    foreground_reference, attrs), each seed's CMB the draw of
    :func:`sky.cmb.band_limited_seed_cmb` and its noise the stream ("map-domain noise", channel,
    seed, detector); the filter's action applied up to ``simulation.filter_lmax`` (at
    most the map's band 3 nside - 1). The operators are computed once, on the first seed.
    ``pooled_h5s``: the fixed passes whose noise shaping is pooled with this one's
    (:func:`config.noise_shaping_siblings`; this channel's file among them): the seeds then use
    :func:`pooled_noise_shaping` of them."""

    def __init__(self, config: dict, fixed_h5, pooled_h5s=()):
        self.config = config
        self.fixed, self.attributes = read_fixed_maps(fixed_h5)
        if len(pooled_h5s) > 1:  # siblings share the systematics: S^h pools like S
            shaping, h_shaping = pooled_noise_shaping(pooled_h5s)
            self.fixed = dataclasses.replace(
                self.fixed, noise_shaping=shaping, noise_h_shaping=h_shaping
            )
        self.name = str(self.attributes["channel"])
        self.fwhm_arcmin = cfg.channel(config, self.name).fwhm_arcmin
        self.lmax = 3 * int(self.attributes["nside"]) - 1
        measured = self.fixed.transfer.shape[1] - 1
        self.filter_lmax = min(config["simulation"]["filter_lmax"] or self.lmax, self.lmax)
        if measured < self.filter_lmax:
            raise ValueError(
                f"{fixed_h5}: the fixed pass measured the filter up to ell = {measured}, but "
                f"simulation.filter_lmax asks for {self.filter_lmax}: rerun its fixed_pass rule"
            )
        # sqrt(N / N_e) on the map's binned noise for an emulated focal plane, else 1
        self.map_noise_factor = float(np.sqrt(cfg.emulated_pairs_factor(config, self.name)))
        self._operators = None

    @classmethod
    def from_run(cls, config: dict, fixed_h5) -> ChannelSeeds:
        """As the workflow makes them: the noise shaping pooled over the fixed passes of
        :func:`config.noise_shaping_siblings` in the same run folder (``<maps>/<channel>/<the
        same file name>``; those not made are left out, with a warning)."""
        fixed_h5 = Path(fixed_h5)
        name = read_fixed_attribute(fixed_h5, "channel")
        pooled = []
        for sibling in cfg.noise_shaping_siblings(config, name):
            path = fixed_h5.parent.parent / sibling / fixed_h5.name
            if path.exists():
                pooled.append(path)
            else:
                log.warning("%s: no fixed pass %s to pool its noise shaping with", name, path)
        return cls(config, fixed_h5, pooled)

    @property
    def operators(self) -> SeedOperators:
        """The :class:`SeedOperators` the seeds share (built on first use)."""
        if self._operators is None:
            noise_scale = self.config["simulation"]["noise_scale"]
            self._operators = SeedOperators(self.fixed, noise_scale, self.filter_lmax)
        return self._operators

    @property
    def fixed_templates(self) -> np.ndarray:
        """(n_det, 3, npix) the fixed pass's templates T_k at the channel's A_2 [K_CMB^2],
        zero off its good pixels: a seed's templates minus these are its seed part."""
        a2_k_cmb = float(self.attributes["a2_k_cmb"])
        terms = self.fixed.template_terms
        return np.where(self.fixed.good, templates_from_terms(terms, a2_k_cmb), 0.0)

    def cmb_excess_alm(self, seed: int) -> np.ndarray | None:
        """(2, 3, nalm) the filters' excess BB of ``seed`` at band ``filter_lmax``
        (:func:`filter_response.excess_bb_alms` of the pass's E_ell at the channel's beam):
        of B origin on the model BB at the seed's r (``simulation.cmb_r``), which scales
        the sky's B modes; of T and E origin on the model BB at the r of the pass's
        reference CMB (attribute ``cmb_r``; the seed's r in a pass that lacks it), which it
        was measured against, so that the leakage does not grow with the seed's r (the T
        and E modes it comes from do not); None if the pass did not measure it."""
        if not self.fixed.cmb_bb_excess.size:
            return None
        lmax = self.filter_lmax
        seed_r = self.config["simulation"]["cmb_r"]
        pass_r = float(self.attributes.get("cmb_r", seed_r))
        reference_bb = [sky_cmb.cmb_spectra(r, lmax)[2] for r in (seed_r, pass_r)]
        units = sky_cmb.filter_excess_unit_alms(lmax, self.config["master_seed"], seed)
        return self._beamed_excess(np.array(reference_bb), units)

    def _beamed_excess(self, reference_bb_k2: np.ndarray, units: np.ndarray) -> np.ndarray:
        """:func:`filter_response.excess_bb_alms` of the pass's first len(units) E_ell rows
        on ``reference_bb_k2`` (band ``filter_lmax``; one spectrum, or one per row) at the
        channel's beam."""
        lmax = self.filter_lmax
        beam = hp.gauss_beam(np.radians(self.fwhm_arcmin / 60.0), lmax=lmax, pol=True)[:, 2]
        excess = self.fixed.cmb_bb_excess[: len(units)]
        reference = np.atleast_2d(reference_bb_k2)[:, : lmax + 1] * beam**2
        return excess_bb_alms(excess, units, reference, lmax)

    def tensor_alms(self, seed: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(the tensor probe's a_lm at band ``lmax``, its filters' excess of B origin at
        band ``filter_lmax``) of ``seed`` (:func:`realize_seed`'s ``tensor_alms``); None if
        the pass did not measure the excess (the seeds then carry no B modes alone)."""
        if not self.fixed.cmb_bb_excess.size:
            return None
        master_seed = self.config["master_seed"]
        alm = sky_cmb.tensor_b_alm(self.lmax, master_seed, seed, self.fwhm_arcmin)
        band = sky_cmb.beam_band_limit(self.fwhm_arcmin, self.lmax)
        unit = sky_cmb.tensor_excess_unit_alm(self.filter_lmax, master_seed, seed)[None]
        excess = self._beamed_excess(sky_cmb.tensor_bb_r1(self.filter_lmax), unit)[0]
        return hp.resize_alm(alm, self.lmax, self.lmax, band, band), excess

    def noise_generator(self, seed: int):
        """rng_of_detector(k) of a seed: detector k's stream ("map-domain noise", channel,
        seed, detector)."""
        detectors = list(self.attributes["detectors"])
        master_seed = self.config["master_seed"]

        def rng_of_detector(k):
            return seeding.rng(master_seed, "map-domain noise", self.name, seed, detectors[k])

        return rng_of_detector

    def maps(self, seed: int, full_terms: bool = True) -> dict:
        """The maps of ``seed`` (:func:`realize_seed`; ``full_terms`` passed on)."""
        simulation, master_seed = self.config["simulation"], self.config["master_seed"]
        cmb_alm, band = sky_cmb.band_limited_seed_cmb(
            self.lmax, simulation["cmb_r"], master_seed, seed, self.fwhm_arcmin
        )
        maps = realize_seed(
            self.fixed,
            cmb_alm,
            band,
            float(self.attributes["a2_k_cmb"]),
            simulation["noise_scale"],
            self.noise_generator(seed),
            self.operators,
            full_terms,
            self.cmb_excess_alm(seed),
            self.tensor_alms(seed),
            self.map_noise_factor,
        )
        maps["attrs"] = {**self.attributes, "seed": seed, "realization": "map_domain"}
        return maps


def pooled_noise_shaping(fixed_h5s) -> tuple[np.ndarray, np.ndarray]:
    """(S_ell, S^h_ell) pooled over fixed passes whose shaping is the same by construction
    (:func:`config.noise_shaping_siblings`): S = sqrt(sum_c K_c S_c^2 / sum_c K_c), K_c the
    noise reference realizations of file c (its ``noise_reference_realizations``
    attribute, 1 if absent). Each S_c^2 is a ratio of pseudo-spectra summed over its
    realizations, so the pooled one averages sum_c K_c of them: its scatter at low ell
    (a realization's S^2 differs by 30 % to 3x at ell 2-11) falls as 1 / sqrt(sum K_c).
    S^h pools the files that carry systematics; (0,) if none does."""
    if not fixed_h5s:
        raise ValueError("pooled_noise_shaping: no fixed pass files given")
    sums = {"noise_shaping": [0.0, 0.0], "noise_h_shaping": [0.0, 0.0]}
    shape = None
    for path in fixed_h5s:
        with h5py.File(path) as stored:
            weight = float(stored.attrs.get("noise_reference_realizations", 1))
            for name, total in sums.items():
                if name not in stored or stored[name].size == 0:
                    continue
                values = stored[name][()]
                shape = shape or values.shape
                if values.shape != shape:
                    raise ValueError(
                        f"{path}: {name} of shape {values.shape}, the other pooled fixed "
                        f"passes' {shape} (measured to another ell): rerun its fixed_pass rule"
                    )
                total[0] += weight * values**2
                total[1] += weight
    pooled = [
        np.sqrt(total / weight) if weight else np.zeros(0)
        for total, weight in (sums["noise_shaping"], sums["noise_h_shaping"])
    ]
    return pooled[0], pooled[1]
