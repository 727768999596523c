"""Where on the sky: the residual binned in Galactic pixels against the nominal sky
(:mod:`hwp_tes_systematics.diagnose.locate`, "Sky")."""

from __future__ import annotations

import math

import numpy as np

from ..model import Context, coarse_pixels

SKY_NSIDE = 32


def bin_map(pixels, values, valid, npix):
    hits = np.bincount(pixels[valid], minlength=npix)
    sums = np.bincount(pixels[valid], weights=values[valid], minlength=npix)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(hits > 0, sums / np.maximum(hits, 1), np.nan), hits


def sky_residual(residual: np.ndarray, ctx: Context, sigma_sample: np.ndarray) -> dict:
    """Residual map and its correlation with the intensity and dipole maps (all detectors)."""
    pixels, nside = coarse_pixels(ctx, SKY_NSIDE)
    if pixels is None:
        return {"available": False}
    npix = 12 * nside * nside
    valid = ctx.valid.ravel()
    pix = pixels.ravel()
    weights = np.repeat(1.0 / np.asarray(sigma_sample) ** 2, ctx.n_samples)
    hits = np.bincount(pix[valid], minlength=npix)
    wsum = np.bincount(pix[valid], weights=weights[valid], minlength=npix)

    def weighted(values):
        sums = np.bincount(pix[valid], weights=(values.ravel() * weights)[valid], minlength=npix)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(hits > 0, sums / np.maximum(wsum, 1e-300), np.nan)

    # the offset is a nuisance (DC is not fitted): remove each detector's mean first
    centred = (
        residual
        - np.array([residual[k][ctx.valid[k]].mean() for k in range(ctx.n_detectors)])[:, None]
    )
    residual_map = weighted(centred)
    intensity_map = weighted(ctx.sky_intensity)
    dipole_map = weighted(ctx.dipole)
    seen = hits > 0
    noise_map = np.where(seen, 1.0 / np.sqrt(np.maximum(wsum, 1e-300)), np.nan)
    out = {"available": True, "nside": nside, "n_pixels": int(seen.sum())}
    if seen.sum() < 5:
        return out | {"residual_map": residual_map, "hits": hits}
    for name, template in (("intensity", intensity_map), ("dipole", dipole_map)):
        x, y, e = template[seen], residual_map[seen], noise_map[seen]
        if np.std(x) == 0 or np.std(y) == 0:
            r = 0.0
        else:
            r = float(np.corrcoef(x, y)[0, 1])
        z = float(np.arctanh(np.clip(r, -0.999999, 0.999999)) * math.sqrt(max(seen.sum() - 3, 1)))
        design = np.column_stack([x - x.mean(), np.ones_like(x)]) / e[:, None]
        coefficients, *_ = np.linalg.lstsq(design, y / e, rcond=None)
        cov = np.linalg.pinv(design.T @ design)
        out[name] = {
            "correlation": r,
            "fisher_z_sigma": z,
            "coefficient": float(coefficients[0]),
            "sigma_coefficient": float(math.sqrt(max(cov[0, 0], 0.0))),
        }
    out["residual_map"] = residual_map
    out["hits"] = hits
    return out
