"""The fixed TOD pass against a reference written by the code before the speed-ups.

One M1-140 pair, four hours in two-hour chunks at 19 Hz, the sky scanned from its a_lm at
nside 8, five map-makers in one pass: binned with 60 s baselines at nside 8 and 4,
binned without baselines at nside 8, and HWP demodulation with and without baselines at
nside 8. Every product of every map-maker (maps, template terms, references, matrices,
moments, hits, the filter's transfer and noise shaping) must equal the reference to
rounding: the speed-ups reorder sums and reuse memory, they do not change the numbers.

The reference (tests/data/fixed_pass_reference.npz) was written at commit c508fb9 with

    PYTHONPATH=<checkout of c508fb9>/src:tests python tests/simulation/test_fixed_pass_reference.py \
        tests/data/fixed_pass_reference.npz
"""

import sys
from pathlib import Path

import healpy as hp
import numpy as np
import pytest
from helpers import m1_140_pair, pipeline_settings

from hwp_tes_systematics.sky import cmb as sky_cmb

REFERENCE = Path(__file__).parents[1] / "data" / "fixed_pass_reference.npz"
SCAN_NSIDE, LMAX = 8, 23
BINNED = [(4, 60.0), (8, None)]
DEMODULATED = [(8, 60.0), (8, None)]
# float64 products: sums reordered (the harmonic fit's projections, the binning's order)
DOUBLE_RTOL = 1e-9
# T_ell and S_ell come from the calibration TODs filtered in float32 (of order 1)
SINGLE_ATOL = 2e-5
SINGLE_PRECISION = ("transfer", "noise_shaping", "noise_h_shaping", "cmb_h_transfer")
SINGLE_PRECISION += ("cmb_s_shaping",)
# products measured after the reference was written (their physics is tested elsewhere:
# tests/simulation/test_map_domain.py::test_the_bb_excess_is_what_the_filter_adds_beyond_the_transfer)
LATER_FIELDS = ("cmb_bb_excess",)
# fields whose rows changed definition after it: the transfer's BB, now from the reference's
# B modes alone (filter_response.measure_cmb_response; tested in tests/simulation/test_map_domain.py)
LATER_ROWS = {"transfer": slice(0, 2)}


def fixed_pass_products() -> dict[str, np.ndarray]:
    """{'<variant>/<field>': array} of every map-maker of the pass (see the docstring)."""
    import dataclasses

    from hwp_tes_systematics import sky
    from hwp_tes_systematics.simulation import fixed_maps

    simulator = m1_140_pair(4 * 3600.0, 2 * 3600.0, SCAN_NSIDE, 19.0, noise_model="keshner")
    settings = pipeline_settings(simulator, seed=fixed_maps.NOISE_REFERENCE_SEED, noise_scale=0.0)
    cls = np.zeros((4, LMAX + 1))
    cls[:3, 2:] = 1e-9 * (np.arange(2, LMAX + 1) / 10.0) ** -2.5
    foreground = hp.alm2map(sky.gaussian_alm(cls, LMAX, np.random.default_rng(3)), SCAN_NSIDE)
    foreground[0] += 3e-3  # an intensity offset as large as the dipole
    transfer_alm = sky_cmb.transfer_cmb_alm(LMAX, 0.0, 7, simulator.channel.fwhm_arcmin)
    passes = fixed_maps.fixed_passes(
        simulator,
        settings,
        foreground,
        transfer_alm,
        True,
        LMAX,
        extra_variants=BINNED,
        demodulated_variants=DEMODULATED,
        band_limited_sky=True,
    )
    products = {}
    for variant, fixed in passes.items():
        label = "_".join(str(part) for part in variant)
        for field in dataclasses.fields(fixed):
            value = getattr(fixed, field.name)
            if isinstance(value, np.ndarray):
                products[f"{label}/{field.name}"] = value
    return products


@pytest.mark.slow
def test_the_fixed_pass_equals_the_reference_to_rounding():
    expected = dict(np.load(REFERENCE))
    products = {
        key: value
        for key, value in fixed_pass_products().items()
        if key.split("/")[1] not in LATER_FIELDS
    }
    assert sorted(products) == sorted(expected)
    for key, value in products.items():
        reference = expected[key]
        assert value.shape == reference.shape, key
        rows = LATER_ROWS.get(key.split("/")[1])
        if rows is not None:
            value, reference = value[rows], reference[rows]
        if value.dtype == bool:
            np.testing.assert_array_equal(value, reference, err_msg=key)
            continue
        if key.split("/")[1] in SINGLE_PRECISION:  # spectra: ell >= 2 (0 and 1 carry no sky)
            value, reference = value[..., 2:], reference[..., 2:]
        finite = np.abs(reference) < 1e20  # hp.UNSEEN and infinite conditions aside
        np.testing.assert_array_equal(finite, np.abs(value) < 1e20, err_msg=key)
        if not finite.any():
            continue
        scale = np.abs(reference[finite]).max()
        tolerance = SINGLE_ATOL if key.split("/")[1] in SINGLE_PRECISION else DOUBLE_RTOL * scale
        np.testing.assert_allclose(
            value[finite], reference[finite], rtol=0, atol=tolerance, err_msg=key
        )


if __name__ == "__main__":  # write the reference (see the module docstring)
    np.savez_compressed(sys.argv[1], **fixed_pass_products())
