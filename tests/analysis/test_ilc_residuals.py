"""The systematic-only estimator and the beam consistency of the residual spectra."""

import h5py
import healpy as hp
import numpy as np
import pandas as pd
import pytest

from hwp_tes_systematics import sky
from hwp_tes_systematics.analysis import hilc, requirement
from hwp_tes_systematics.analysis.ilc_residuals import SeedMaps, systematic_bb, unit_beam_spectra
from hwp_tes_systematics.analysis.likelihood import BBModel, fisher_bias, fit_r
from hwp_tes_systematics.analysis.systematics import case_names, maps_for_sigma
from hwp_tes_systematics.config import deep_merge, load_config
from hwp_tes_systematics.simulation import fixed_maps, map_domain
from hwp_tes_systematics.simulation.mapmaking import MATRIX_ENTRIES
from hwp_tes_systematics.simulation.maps_file import read_channel_maps
from hwp_tes_systematics.simulation.tod_maps import templates_from_terms
from hwp_tes_systematics.sky import cmb as sky_cmb
from hwp_tes_systematics.stages import component_separation

NSIDE = 16
CHANNELS = {"L1-040": 0.0, "M1-140": 0.26}  # channel: A_2 [K_CMB]


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory, repo):
    """(config, {channel: maps file}): synthetic pair_maps files of two channels, a common
    CMB-like sky, channel noise and random template terms; the HILC set-up of the workflow
    on the full sky."""
    config = deep_merge(
        load_config(repo / "config/config.yaml"),
        {
            "instrument": {"channels": list(CHANNELS), "systematics_channels": ["M1-140"]},
            "maps": {"nside": NSIDE},
            "component_separation": {"galactic_cut_deg": 0.0, "mask_apodization_deg": 0.0},
        },
    )
    folder = tmp_path_factory.mktemp("synthetic_maps")
    rng = np.random.default_rng(5)
    npix = hp.nside2npix(NSIDE)
    cmb = rng.normal(size=(3, npix)) * 1e-6
    paths = {}
    for name, a2_k in CHANNELS.items():
        paths[name] = str(folder / f"{name}.h5")
        terms = rng.normal(size=(3, 2, 3, npix)) * np.array([1e-6, 1e-4, 1e-3])[:, None, None, None]
        with h5py.File(paths[name], "w") as out:
            out["nosys"] = cmb + rng.normal(size=(3, npix)) * 1e-6
            out["template_terms"] = terms
            out["templates"] = templates_from_terms(terms, a2_k)
            out["cmb_reference"] = cmb
            out["foreground_reference"] = np.zeros((3, npix))
            out.attrs.update({"detectors": ["det_a", "det_b"], "a2_k_cmb": a2_k})
    return config, paths


@pytest.fixture(scope="module")
def seed_maps(synthetic):
    config, paths = synthetic
    return SeedMaps.load(config, 0, paths)


@pytest.fixture(scope="module")
def channel_maps(synthetic):
    """The synthetic channels' maps, in the order of SeedMaps' channels."""
    _, paths = synthetic
    return [read_channel_maps(path) for path in paths.values()]


def test_component_separation_stage_writes_every_case_and_the_systematic(synthetic, tmp_path):
    """One job per seed: a file per case, and the systematic-only spectra through the
    no-systematics weights of that same job (the maps read once)."""
    config, paths = synthetic
    cases = case_names(config["requirement"]["sigma_g1_per_k"])
    outs = [str(tmp_path / f"{case}.h5") for case in cases]
    csv = tmp_path / "systematic_only.csv"
    component_separation.run(config, 0, cases, paths, outs, str(csv))
    seed_maps = SeedMaps.load(config, 0, paths)
    for case, out in zip(cases, outs, strict=True):
        with h5py.File(out) as hilc:
            assert hilc.attrs["case"] == case
            if case == "nosys":
                weights = hilc["weights"][()]
                residual = hilc["residual_alm"][()]
    expected = seed_maps.systematic_spectra(weights, residual)
    assert "bb_mitigated_k4" in expected  # the template fit of the default config
    written = pd.read_csv(csv)
    assert list(written.columns) == list(expected.columns)
    np.testing.assert_allclose(written.to_numpy(), expected.to_numpy(), rtol=1e-9, atol=0)
    with pytest.raises(ValueError, match="nosys"):
        component_separation.run(config, 0, cases[1:], paths, outs[1:], str(csv))


def direct_systematic_bb(seed_maps, channel_maps, weights, sigma, a2_scale=1.0):
    """BB of sigma sum_c w_c sum_k z_ck T_ck(a A_2), straight from the maps."""
    maps = []
    for data, draws in zip(channel_maps, seed_maps.unit_draws, strict=True):
        a2_k = a2_scale * data["attrs"]["a2_k_cmb"]
        templates = templates_from_terms(data["template_terms"], a2_k)
        maps.append(maps_for_sigma(np.zeros_like(data["nosys"]), templates, draws, sigma))
    alm = hilc.apply_ilc(seed_maps.alms(maps), weights, seed_maps.bins, seed_maps.lmax)
    return unit_beam_spectra(
        alm, None, seed_maps.lmax, seed_maps.fractions["w2"], seed_maps.common_fwhm_arcmin
    )[2]


def test_systematic_only_is_exactly_quadratic(seed_maps, channel_maps):
    weights = seed_maps.residual(0.0)["weights"]
    table = seed_maps.systematic_spectra(weights)
    model = BBModel.from_ptep(f_sky=1.0, lmax=seed_maps.lmax, n_ell=1e-16)
    for a2_scale in (1.0, 0.5, 3.0):
        unit = systematic_bb(table, a2_scale)
        direct = direct_systematic_bb(seed_maps, channel_maps, weights, 1.0, a2_scale)
        assert np.abs(unit - direct)[2:].max() < 1e-10 * np.abs(direct).max()
    sigmas = np.logspace(-4, -1, 4)
    delta_r = [fisher_bias(sigma**2 * systematic_bb(table), model) for sigma in sigmas]
    _, exponent, _ = requirement.fit_power_law(sigmas, delta_r)
    assert exponent == pytest.approx(2.0, abs=1e-6)
    # and the spectrum of the systematic at sigma, straight from the maps, follows it
    direct = [
        fisher_bias(direct_systematic_bb(seed_maps, channel_maps, weights, sigma), model)
        for sigma in sigmas
    ]
    np.testing.assert_allclose(direct, delta_r, rtol=1e-8)


def test_beamed_cmb_residual_recovers_r():
    """A B-mode sky of r_in = 0.01 (exact power per ell), smoothed by the 70.5' common beam
    as the HILC residual is: the beam-deconvolved spectrum gives back r_in; without the
    deconvolution r would come out ~20 % low."""
    r_in, lmax, nside, fwhm = 0.01, 64, 64, 70.5
    c_bb = r_in * sky.tensor_bb_r1(lmax)
    ell, m = hp.Alm.getlm(lmax)
    phases = np.exp(2j * np.pi * np.random.default_rng(1).random(ell.size))
    alm = np.zeros((3, ell.size), dtype=complex)
    alm[2] = np.sqrt(c_bb[ell]) * np.where(m > 0, phases, 1.0)  # |a_lm|^2 = C_ell exactly
    maps = hp.alm2map(hilc.deconvolve_to_common_beam(alm, 0.0, fwhm, lmax), nside, lmax=lmax)
    masked = hilc.maps_to_alm(maps, np.ones(hp.nside2npix(nside)), lmax)
    c_res = unit_beam_spectra(masked, None, lmax, 1.0, fwhm)[2]
    model = BBModel(
        ell=np.arange(lmax + 1),
        c_lens=sky.lensing_bb(lmax),
        c_gw_r1=sky.tensor_bb_r1(lmax),
        c_fg_res=0.0,
        n_ell=0.0,
        f_sky=1.0,
        lmax=lmax,
    )
    assert fit_r(c_res, model).r_ml == pytest.approx(r_in, rel=0.02)
    beamed = unit_beam_spectra(masked, None, lmax, 1.0, 0.0)[2]
    assert fit_r(beamed, model).r_ml < 0.9 * r_in


def test_data_alms_by_linearity_equal_the_transform_of_each_case(seed_maps, channel_maps):
    """a(m_nosys) + sigma a(sum z T) (computed once per realization) is the a_lm of each
    case's contaminated maps transformed directly, to round-off."""
    for sigma in (0.0, 1e-3, 0.1):
        maps = [
            maps_for_sigma(data["nosys"], data["templates"], draws, sigma)
            for data, draws in zip(channel_maps, seed_maps.unit_draws, strict=True)
        ]
        direct = seed_maps.alms(maps)
        np.testing.assert_allclose(
            seed_maps.data_alms(sigma), direct, rtol=0, atol=1e-12 * np.abs(direct).max()
        )


def test_map2alm_iter_zero_changes_the_residual_spectra_little(seed_maps, synthetic):
    """component_separation.map2alm_iter: the residual BB of one Jacobi-free analysis
    (0, one transform per map) is that of 3 iterations within 1 % per band of 10 ell."""
    assert seed_maps.map2alm_iter == 3
    iterated = seed_maps.residual_spectra(1e-3)["bb_residual_k2"].to_numpy()
    config, paths = synthetic
    config = deep_merge(config, {"component_separation": {"map2alm_iter": 0}})
    plain = SeedMaps.load(config, 0, paths)
    once = plain.residual_spectra(1e-3)["bb_residual_k2"].to_numpy()
    bands = slice(2, 2 + 10 * ((len(once) - 2) // 10))
    ratio = once[bands].reshape(-1, 10).sum(axis=1) / iterated[bands].reshape(-1, 10).sum(axis=1)
    np.testing.assert_allclose(ratio, 1.0, atol=0.01)
    assert not np.array_equal(once, iterated)


def test_fixed_instrument_spectra_match_the_direct_spectra(seed_maps):
    """With the seed's own draws as the instrument, the auto spectrum is the systematic-only
    BB (bb_unit_k4); the cross spectrum with the no-systematics residual is
    (C[R + S] - C[R] - C[S]) / 2 of the a_lm combined directly."""
    nosys = seed_maps.residual(0.0)
    table = seed_maps.instrument_spectra(nosys, [seed_maps.unit_draws])
    unit = seed_maps.systematic_spectra(nosys["weights"])
    np.testing.assert_allclose(table["bb_auto_instrument0_k4"], unit["bb_unit_k4"], rtol=1e-10)
    template = seed_maps.systematic_term_alms(nosys["weights"]).sum(axis=0)
    residual = nosys["residual_alm"]

    def bb(alm):
        return unit_beam_spectra(
            alm, None, seed_maps.lmax, seed_maps.fractions["w2"], seed_maps.common_fwhm_arcmin
        )[2]

    direct = (bb(residual + template) - bb(residual) - bb(template)) / 2
    np.testing.assert_allclose(
        table["bb_cross_instrument0_k3"], direct, rtol=1e-8, atol=1e-12 * np.abs(direct).max()
    )
    assert np.any(table["bb_cross_instrument0_k3"] != table["bb_cross_unfiltered_instrument0_k3"])
    # the template fit (the default config's) knows these templates whole: of a g1 common
    # to every detector it leaves rounding
    common, after = (
        table[f"bb_auto_{name}_k4"].abs().max()
        for name in ("common_offset", "common_offset_mitigated")
    )
    assert after < 1e-20 * common


def test_component_separation_writes_the_fixed_instruments(synthetic, tmp_path):
    """Three fixed instruments: their draws differ from the seed's and from each other,
    and the table holds one auto and two cross spectra each."""
    config, paths = synthetic
    cases = case_names(config["requirement"]["sigma_g1_per_k"])
    outs = [str(tmp_path / f"{case}.h5") for case in cases]
    csv = tmp_path / "instruments.csv"
    component_separation.run(
        config, 0, cases, paths, outs, str(tmp_path / "s.csv"), None, str(csv), 3
    )
    table = pd.read_csv(csv)
    autos = [table[f"bb_auto_instrument{i}_k4"].to_numpy() for i in range(3)]
    assert len({round(float(a[2:].sum()), 30) for a in autos}) == 3
    assert all(f"bb_cross_unfiltered_instrument{i}_k3" in table for i in range(3))


def test_channel_alms_files_keep_each_detector_and_refuse_summed_terms(synthetic, tmp_path):
    """A stored channel's terms are per detector (any draws combine them); a file of the
    older layout (terms already summed over the seed's draws) is refused by name."""
    from hwp_tes_systematics.analysis import channel_alms as ca

    config, paths = synthetic
    seed_maps = SeedMaps.load(config, 0, paths)
    harmonic = ca.HarmonicSettings.from_config(config)
    data = read_channel_maps(paths["M1-140"])
    channel = ca.ChannelAlms.from_maps(config, 0, "M1-140", data, seed_maps.mask, harmonic)
    assert channel.alms["x1"].shape[0] == 2
    path = tmp_path / "M1-140.h5"
    ca.write_channel_alms(path, channel, ca.alms_attributes(0, harmonic, seed_maps.mask))
    stored = ca.read_channel_alms(path, harmonic, float(seed_maps.mask.sum()))
    np.testing.assert_array_equal(stored.term("x1"), channel.term("x1"))
    with h5py.File(path, "r+") as out:
        summed = out["alm_x1"][()].sum(axis=0)
        del out["alm_x1"]
        out["alm_x1"] = summed
    with pytest.raises(ValueError, match="alm_x1.*older map_domain_alms"):
        ca.read_channel_alms(path, harmonic, float(seed_maps.mask.sum()))


def test_template_split_sums_to_the_systematic(synthetic):
    """Map-domain a_lm carry the seed's two pieces of the s h term: the split's parts
    (fixed, cmb_h, noise_h) sum to the whole systematic, and their auto and cross BB
    (each cross twice) to bb_unit_k4."""
    from hwp_tes_systematics.analysis import channel_alms as ca

    config, paths = synthetic
    mask = SeedMaps.load(config, 0, paths).mask
    harmonic = ca.HarmonicSettings.from_config(config)
    rng = np.random.default_rng(9)
    channels = []
    for name, path in paths.items():
        data = read_channel_maps(path)
        shape = data["template_terms"][1].shape
        data["sh_term_pieces"] = {
            "cmb_h": 0.3 * data["template_terms"][1] + rng.normal(size=shape) * 1e-5,
            "noise_h": rng.normal(size=shape) * 1e-4,
        }
        channels.append(ca.ChannelAlms.from_maps(config, 0, name, data, mask, harmonic))
    seed_maps = SeedMaps.combine(config, 0, channels, mask, harmonic)
    weights = seed_maps.residual(0.0)["weights"]
    parts = seed_maps.template_split_alms(weights)
    whole = seed_maps.systematic_term_alms(weights).sum(axis=0)
    np.testing.assert_allclose(sum(parts.values()), whole, rtol=1e-12, atol=0)
    table = seed_maps.systematic_spectra(weights)
    summed = sum(
        (1 if a == b else 2) * table[f"bb_{a}_x_{b}_k4"]
        for i, a in enumerate(ca.TEMPLATE_PARTS)
        for b in ca.TEMPLATE_PARTS[i:]
    )
    np.testing.assert_allclose(summed, table["bb_unit_k4"], rtol=1e-9, atol=1e-30)
    assert np.all(table["bb_noise_h_x_noise_h_k4"][2:] > 0)


def synthetic_fixed_pass(nside: int, rng) -> fixed_maps.FixedMaps:
    """A map-domain fixed pass of two detectors on a random sky: HWPSS moments from eight
    random HWP angles per pixel, random template terms, a few pixels not good."""

    npix, lmax = hp.nside2npix(nside), 3 * nside - 1
    moments = np.zeros((2, npix, 3, 6))
    for k in range(2):
        for _ in range(8):
            chi = rng.uniform(0, 2 * np.pi, npix)
            a = np.stack([np.ones(npix), np.cos(4 * chi), np.sin(4 * chi)])
            for entry, (i, j) in enumerate(MATRIX_ENTRIES):
                for weight in range(3):
                    moments[k, :, weight, entry] += np.cos(2 * chi) ** weight * a[i] * a[j]
    good = np.ones(npix, bool)
    good[rng.choice(npix, 20, replace=False)] = False
    scales = np.array([1e-6, 1e-4, 1e-3])[:, None, None, None]
    return fixed_maps.FixedMaps(
        nosys=rng.normal(size=(3, npix)) * 1e-6,
        template_terms=rng.normal(size=(3, 2, 3, npix)) * scales,
        foreground_reference=rng.normal(size=(3, npix)) * 1e-7,
        transfer=np.full((3, lmax + 1), 0.8),
        noise_shaping=np.full((3, lmax + 1), 0.9),
        noise_h_shaping=np.full((3, lmax + 1), 0.4),
        matrix=moments[:, :, 0].sum(axis=0).T.copy(),
        moments=moments,
        hits=np.full(npix, 16.0),
        condition=np.full(npix, 2.0),
        good=good,
        carries_systematics=True,
    )


def test_seed_alms_from_the_fixed_terms_equal_those_of_the_full_terms(synthetic):
    """A map-domain seed made without its template terms, with the fixed pass's term a_lm
    transformed once (ilc_residuals.fixed_term_alms), gives the a_lm of the seed made with
    them, to round-off (the a_lm are linear in the maps); without the fixed term a_lm it
    is refused by name."""
    from hwp_tes_systematics.analysis import channel_alms as ca

    config, paths = synthetic
    seed_maps = SeedMaps.load(config, 0, paths)
    harmonic = ca.HarmonicSettings.from_config(config)
    a2_k = CHANNELS["M1-140"]
    fixed = synthetic_fixed_pass(NSIDE, np.random.default_rng(11))
    mask = np.where(fixed.good, seed_maps.mask, 0.0)
    lmax = 3 * NSIDE - 1
    cmb_alm = sky_cmb.seed_cmb_alm(lmax, 0.01, 7, 0, 30.0)
    known = ca.fixed_term_alms(config, "M1-140", fixed, a2_k, mask, harmonic)
    made = {}
    for full_terms in (True, False):
        maps = map_domain.realize_seed(
            fixed,
            cmb_alm,
            lmax,
            a2_k,
            1.0,
            lambda k: np.random.default_rng([3, k]),
            None,
            full_terms,
        )
        assert ("template_terms" in maps) == full_terms
        maps["attrs"] = {"detectors": ["det_a", "det_b"], "a2_k_cmb": a2_k}
        given = {} if full_terms else dict(known)
        made[full_terms] = ca.ChannelAlms.from_maps(
            config, 0, "M1-140", maps, mask, harmonic, given
        )
    full, shared = made[True].alms, made[False].alms
    assert set(full) == set(shared)
    assert ca.FIXED_SH_KIND not in shared
    for kind, alm in full.items():
        scale = np.abs(alm).max()
        assert scale > 0, kind
        np.testing.assert_allclose(shared[kind], alm, rtol=0, atol=1e-12 * scale, err_msg=kind)
    with pytest.raises(ValueError, match="missing.*x1_fixed"):
        ca.ChannelAlms.from_maps(config, 0, "M1-140", maps, mask, harmonic, {})
