"""A wider notch takes more of the sky: the information on r falls as delta f grows.

The notch removes what the TOD holds within delta f = 4 f_HWP / D of 4 f_HWP; the sky's
polarization sits there, at 4 f_HWP plus the scan's frequencies, so a wider notch (a
smaller D) removes larger angular scales of it. One M1-140 pair scans the B modes of a
CMB sky alone for one day without noise (nside 16, 19 Hz), through the map-making of
config/one_year.yaml at D = 100 (the paper), 50 and 30, and with no notch (the
4 f_HWP line fitted as an HWP harmonic instead, config/keep_sky.yaml). The BB the map
keeps over the input's, P_ell, on the same pixels, makes the Fisher sigma_r of a
white-noise experiment; it must grow as the notch widens.
"""

import itertools

import healpy as hp
import numpy as np
import pytest
from helpers import m1_140_pair, pipeline_settings

from hwp_tes_systematics import sky
from hwp_tes_systematics.analysis.likelihood import BBModel
from hwp_tes_systematics.simulation.filter_response import b_modes_alone
from hwp_tes_systematics.simulation.mapmaking import solve_maps
from hwp_tes_systematics.simulation.tod_maps import accumulate, split_solved_maps

pytestmark = pytest.mark.slow

NSIDE = 16
LMAX = 3 * NSIDE - 1
# N_ell of the white-noise experiment the transfer is read with [K^2]: ~ LiteBIRD's
# combined depth, 2 uK arcmin (assumption: the ordering, not the value, is tested)
N_ELL_K2 = (2e-6 * np.pi / (180 * 60)) ** 2
FILTERS = {  # name: (notch width divisor D, HWP harmonics removed)
    "no notch": (None, (2, 4)),
    "D = 100": (100.0, (2,)),
    "D = 50": (50.0, (2,)),
    "D = 30": (30.0, (2,)),
}


@pytest.fixture(scope="module")
def b_power_kept():
    """{filter: P_ell on ell = 0..LMAX}, the filtered B map's BB over the input's."""
    simulator = m1_140_pair(86400.0, 86400.0, NSIDE, 19.0, noise_model="keshner")
    cls = np.zeros((4, LMAX + 1))
    cls[2] = sky.lensing_bb(LMAX) + sky.tensor_bb_r1(LMAX)
    alm = b_modes_alone(sky.gaussian_alm(cls, LMAX, np.random.default_rng(5)))
    b_sky = hp.alm2map(alm, NSIDE, lmax=LMAX)
    kept = {}
    for name, (divisor, harmonics) in FILTERS.items():
        settings = pipeline_settings(
            simulator,
            noise_scale=0.0,
            notch_width_divisor=divisor,
            removed_hwp_harmonics=harmonics,
        )
        maps, _, _ = solve_maps(accumulate(simulator, settings, b_sky), 100.0)
        filtered = split_solved_maps(maps, 2, 0.0)["nosys"]
        good = np.all(np.isfinite(filtered), axis=0) & (filtered[0] != hp.UNSEEN)
        bb_out = hp.anafast(np.where(good, filtered, 0.0), lmax=LMAX)[2]
        bb_in = hp.anafast(np.where(good, b_sky, 0.0), lmax=LMAX)[2]
        kept[name] = np.where(bb_in > 0, bb_out / np.where(bb_in > 0, bb_in, 1.0), 0.0)
    return kept


def fisher_sigma_r(power_kept: np.ndarray) -> float:
    """sigma_r of r C_GW P + C_lens P + N on ell = 2..LMAX (f_sky 1)."""
    model = BBModel(
        ell=np.arange(LMAX + 1),
        c_lens=sky.lensing_bb(LMAX) * power_kept,
        c_gw_r1=sky.tensor_bb_r1(LMAX) * power_kept,
        c_fg_res=0.0,
        n_ell=N_ELL_K2,
        f_sky=1.0,
    )
    return model.fisher_sigma_r()


def test_sigma_r_grows_as_the_notch_widens(b_power_kept):
    sigma_r = {name: fisher_sigma_r(kept) for name, kept in b_power_kept.items()}
    order = list(FILTERS)  # from no notch to the widest
    assert all(sigma_r[a] < sigma_r[b] for a, b in itertools.pairwise(order)), sigma_r


def test_the_notch_takes_the_large_scales_first(b_power_kept):
    """Without a notch the map keeps the B modes at every scale; with the paper's it loses
    the lowest multipoles first (the scan puts them nearest 4 f_HWP)."""
    low, high = slice(2, 8), slice(LMAX - 15, LMAX + 1)
    free, paper = b_power_kept["no notch"], b_power_kept["D = 100"]
    assert np.mean(free[low]) > 0.5
    assert np.mean(paper[low]) < 0.5 * np.mean(free[low])
    assert np.mean(paper[high]) > np.mean(paper[low])
