"""Nominal-model adjustments: what a nominal model is never exactly right about, fitted on every recording.

A real recording never matches its nominal model exactly: the HWP's 2f amplitude is known
to a few per cent, its phase to a degree, gains to ~1 %, polarisation angles to a
fraction of a degree, the noise level to ~10 %, and the sky map the user supplies is not
the sky. These quantities are fitted on EVERY recording as part of the nominal model
(flat priors), reported under ``nominal_adjustments`` and never offered as discoveries.

Adjusted nominal model, per detector k (x = 2 (chi - theta_k), a = 2 chi - theta_k + psi):

    d = (1 + g) (I(p) + P + D)                              gain g [1]
        + c cos x + s sin x                                 2f HWPSS: A_2' = |A_2 + c + i s|,
                                                            phase phi = atan2(s, A_2 + c) [rad]
        + dtheta 2 rho (Q sin 2a - U cos 2a)                polarisation angle theta + dtheta
        + s_I I(p) + s_P P                                  sky map rescaled (I and P)
        + o + m(p)                                          offset o [K] and sky residual m
    noise: P(f) = 2 w^2 (f^alpha + fk^alpha) / (f^alpha + fmin^alpha)   w, fk, alpha fitted

with P = rho (Q cos 2a + U sin 2a) and D the dipole. The linear terms are fitted by
whitened (Whittle) least squares; o is the mean of the residual; m(p) is the residual
binned in Galactic pixels at ``sky_residual_nside`` (both detectors pooled, the offsets
removed; OFF by default, see ``SKY_RESIDUAL_NSIDE``; its rms at nside 8 is reported
either way). The tolerance for a small unknown sky residual is otherwise: the sky-scale
adjustments (the whole map rescaled, I and P apart), the 1/f noise fit (a faint sky error
is low-frequency power) and, in :mod:`.unexplained`, lines at pure sky frequencies
(spin/precession combinations) below 10 % of the nominal sky signal there. The
noise is the maximum-Whittle-likelihood white + 1/f fit, above 2 f_spin (below, the
sky, the dipole and any slow drift of them would pass for a steep 1/f), to the residual
before the sky
residual is removed (binning also removes 1/f noise and would bias the knee low; a sky
residual left in can only raise the fitted noise), line bins excluded. With a sky
residual, two passes (linear fit -> offsets, sky residual -> noise -> linear fit again);
without (the default), one. The HWP
lines at n f_HWP (n = 1, 3..8: the HWPSS harmonics' templates) are fitted beside the linear terms
and not kept: missing physics (below) is found by the effects, but unmodelled it drove
the polarised sky's scale, whose template is modulated at 4 f_HWP (an 80 mK 4f line on
H3-402: a broad excess at 3-5 Hz, the noise fitted at twice its level); the noise is
fitted without them too (a line off its Fourier bin leaks far beyond the excluded
bins), and the adjustments' covariance is marginalised over them. The linear
adjustments are then refitted jointly with every candidate effect (:mod:`.select`), so an
effect never has to compete with a nominal error.

Where the line is drawn, and why. An ADJUSTMENT is a constant (over the recording),
per-detector change of a quantity the nominal model already has, at the frequencies and
with the shape it already predicts: a 2f HWPSS of another amplitude or phase (A_2 off by
3 %, 1 deg of phase), the whole sky+dipole signal scaled (a gain), a polarisation angle,
the supplied sky rescaled or wrong in a way fixed on the sky, the offset and the
broadband noise level and 1/f shape. MISSING PHYSICS is anything these cannot produce:
power at other HWP harmonics (1f, 3f, 4f, ...); a 2f amplitude that changes in time (HWP
temperature) or with the incoming intensity (2 f_HWP +- f_spin sidebands); a gain that
drifts; a nonlinear response (4f line with the 2f +- f_spin intermodulation, tied to
A_2^2 and A_2 D); transients; lines or bands the nominal model has nowhere. The line
follows identifiability, not size: an adjustment is by construction degenerate with a
nominal error of any size, so offering it as an effect would make every real recording
a "mismatch". Consequences, documented rather than hidden:

* a detector time constant on a pure 2f HWPSS is a 2f phase lag (and a 1/sqrt(1 +
  (2 pi 2 f_HWP tau)^2) amplitude loss): the same signal as a 2f phase error; the
  adjustment reports the equivalent time constant tan(phi) / (2 pi 2 f_HWP); the effect
  ``detector_time_constant`` is selected only when the lag of other frequencies (the 4f
  line of a nonlinearity, the sky band) is seen;
* crosstalk x within a co-pointed orthogonal pair is a gain +x, an A_2 change -x A_2 and
  a polarisation-efficiency change: adjustments;
* the 2f phase is measured relative to 2 (chi - theta_nominal): it includes twice any
  polarisation-angle error, which is measured separately from the sky polarisation only
  (uncertain when the supplied sky is faintly polarised).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import scipy.fft

from ..effects import Effect
from ..effects.hwpss import harmonic_templates
from ..fourier import rfft
from ..linalg import cross, solve_normal
from ..model import Context, coarse_pixels
from ..noise import (
    NOISE_FMIN_SPINS,
    NoiseModel,
    fitted_modes,
    independent_fraction,
    line_exclusion_mask,
    periodogram_scale,
    whittle_fit,
)

# Binning the residual on the sky is NOT done by default (0): fitted apart from the effects it
# also absorbs the slow dipole part of a gain drift (the dipole is fixed on the sky over a
# few hours), which then passes for a 2f modulation. The default tolerance for an unknown
# sky residual is downstream (:mod:`.unexplained`: lines at sky frequencies below 10 % of
# the nominal sky signal there are tolerated) and the sky-scale adjustments.
SKY_RESIDUAL_NSIDE = 0
REPORT_NSIDE = 8  # resolution of the reported sky-residual rms
PASSES = 2
# HWP lines fitted beside the adjustments and not kept (effects find them later): an
# unmodelled line (a nonlinearity's 80 mK 4f on H3-402) otherwise drives the polarised sky's
# scale (its template is modulated at 4 f_HWP), whose sky structure then fills 3-5 Hz
NUISANCE_HARMONICS = np.array([1, 3, 4, 5, 6, 7, 8])


class NominalAdjustments(Effect):
    """Linear nuisance templates of the nominal model (module docstring), always fitted."""

    name = "nominal"
    title = "nominal-model adjustments"
    parameters: ClassVar[dict[str, str]] = {
        "gain": "1",
        "a2_cos": "K",
        "a2_sin": "K",
        "pol_angle": "rad",
        "sky_scale_intensity": "1",
        "sky_scale_polarization": "1",
    }
    kind = "nominal"
    selectable = False

    def templates(self, ctx: Context) -> np.ndarray:
        quadrature = (
            ctx.sky_polarization_quadrature
            if ctx.sky_polarization_quadrature is not None
            else np.zeros_like(ctx.sky_intensity)
        )
        return np.stack(
            [
                ctx.sky_intensity + ctx.sky_polarization + ctx.dipole,
                np.cos(ctx.hwpss_angle),
                np.sin(ctx.hwpss_angle),
                2.0 * quadrature,
                ctx.sky_intensity,
                ctx.sky_polarization,
            ],
            axis=1,
        )


NOMINAL = NominalAdjustments()


@dataclass
class NominalFit:
    """Result of :func:`fit_nominal`; ``context`` is the adjusted nominal model."""

    values: np.ndarray  # (n_det, n_param) linear adjustments
    covariance: np.ndarray  # (n_det, n_param, n_param)
    offsets_k: np.ndarray  # (n_det,)
    offset_sigmas_k: np.ndarray
    noise: list[NoiseModel]
    noise_covariance: list[np.ndarray]  # of (ln w, ln fk, alpha)
    sky_residual_tod: np.ndarray | None  # (n_det, n) m(p(t))
    sky_residual_rms_k: float
    sky_residual_noise_rms_k: float  # rms expected from the white noise alone
    sky_residual_nside: int | None
    sky_residual_pixels: int
    context: Context = field(repr=False)
    base: Context = field(repr=False)
    # valid x the fitted HWP lines n f_HWP (n = 1, 3..8; NUISANCE_HARMONICS), not kept in the
    # model: subtracted from the residual only where its noise is fitted (a strong line cut by
    # a gap, or off its Fourier bin, leaks far beyond its excluded bins)
    nuisance_lines_tod: np.ndarray = field(repr=False, default=None)


def _sky_residual(residual, valid, pixels, npix):
    """Pooled binned map of the residual (n_det, n) and its value at each sample."""
    use = valid.ravel()
    pix = pixels.ravel()[use]
    hits = np.bincount(pix, minlength=npix)
    sums = np.bincount(pix, weights=residual.ravel()[use], minlength=npix)
    sky = np.where(hits > 0, sums / np.maximum(hits, 1), 0.0)
    return sky, hits, sky[pixels] * valid


def fit_nominal(
    ctx: Context,
    tod: np.ndarray,
    noise_start: list[NoiseModel],
    sky_residual_nside: int | None = SKY_RESIDUAL_NSIDE,
    workers: int = 1,
) -> NominalFit:
    """Fit the nominal adjustments of ``tod`` about the nominal model ``ctx`` (module docstring)."""
    n_det, n, fs = ctx.n_detectors, ctx.n_samples, ctx.sampling_rate_hz
    valid = np.asarray(ctx.valid, dtype=bool)
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    modes = fitted_modes(n)
    scale = [periodogram_scale(n, fs, float(valid[k].mean())) for k in range(n_det)]
    residual0 = np.where(valid, tod - ctx.d_nom, 0.0)
    templates = NOMINAL.templates(ctx)
    templates_f = rfft(templates * valid[:, None, :], axis=-1, workers=workers)
    residual0_f = rfft(residual0, axis=-1, workers=workers)

    pixels, nside = (None, None)
    if sky_residual_nside and ctx.pixels is not None:
        pixels, nside = coarse_pixels(ctx, sky_residual_nside)
    noise = list(noise_start)
    noise_cov = [np.full((3, 3), np.nan)] * n_det
    sky_tod = np.zeros((n_det, n))
    sky_f = np.zeros_like(residual0_f)
    n_par = templates.shape[1]
    values = np.zeros((n_det, n_par))
    covariance = np.zeros((n_det, n_par, n_par))
    offsets = np.zeros(n_det)
    sky_map = hits = None
    lines = harmonic_templates(ctx, NUISANCE_HARMONICS)  # (n_det, 2 m, n)
    line_values = np.zeros(lines.shape[:2])
    # the weights (the configured noise) and, without a sky residual, the data do not change
    # between passes: a second pass would repeat the first
    for _ in range(PASSES if pixels is not None else 1):
        for k in range(n_det):
            # weights from the CONFIGURED noise: a noise fitted to a residual that still
            # holds a strong effect (its leakage over the circular FFT) can be far off and
            # would pull the linearisation point of the effects with it
            s = scale[k] * noise_start[k].psd(freqs)
            # v / S_f: a gapped periodogram's modes hold v independent ones each (noise)
            w = np.where(modes, independent_fraction(valid[k]) / np.maximum(s, 1e-300), 0.0)
            # the HWP lines beside them, as nuisances (module docstring), and with flagged
            # samples a constant: masked, it is no longer the DC mode the fit leaves out, and
            # a nonlinearity's g1 A_2^2 / 2 (21 mK on H3-402 at g1 = 3e-3) cut by a gap leaked
            # into the gain, leaving the dipole at f_spin in the residual (fit.GAP_OFFSET)
            parts = [templates_f[k], rfft(lines[k] * valid[k], axis=-1, workers=workers)]
            if not valid[k].all():
                parts.append(rfft(valid[k].astype(float), workers=workers)[None])
            bank = np.concatenate(parts)
            solution, full_covariance = solve_normal(
                cross(bank, bank, w), cross(bank, residual0_f[k] - sky_f[k], w)
            )
            values[k] = solution[:n_par]
            line_values[k] = solution[n_par : n_par + lines.shape[1]]
            covariance[k] = full_covariance[:n_par, :n_par]
        residual1 = residual0 - np.einsum("kj,kjn->kn", values, templates) * valid
        offsets = np.array([residual1[k][valid[k]].mean() for k in range(n_det)])
        residual1 = np.where(valid, residual1 - offsets[:, None], 0.0)
        if pixels is not None:
            sky_map, hits, sky_tod = _sky_residual(residual1, valid, pixels, 12 * nside * nside)
            sky_f = rfft(sky_tod, axis=-1, workers=workers)
        # the noise is fitted BEFORE the sky residual is removed: binning in pixels would
        # also remove 1/f noise (a destriper) and bias the knee low
        # the noise without the lines too: an unmodelled one leaks far beyond its bins
        line_tod = np.einsum("kj,kjn->kn", line_values, lines) * valid
        residual1_f = rfft(residual1 - line_tod, axis=-1, workers=workers)
        noise, noise_cov, _ = refit_noise(ctx, residual1_f, noise)

    offset_sigmas = np.array(
        [math.sqrt(float(m.psd(1.0 / ctx.duration_s)) / ctx.duration_s) for m in noise]
    )
    rms = noise_rms = 0.0
    pixels_used = 0
    subtracted = sky_map is not None
    if sky_map is None and ctx.pixels is not None:  # reported, not subtracted
        pixels_report, nside = coarse_pixels(ctx, REPORT_NSIDE)
        sky_map, hits, _ = _sky_residual(residual1, valid, pixels_report, 12 * nside * nside)
    if sky_map is not None:
        seen = hits > 0
        pixels_used = int(seen.sum())
        rms = float(np.sqrt(np.mean(sky_map[seen] ** 2)))
        sigma2 = np.mean([m.net_k_sqrt_s**2 * fs for m in noise])
        noise_rms = float(np.sqrt(np.mean(sigma2 / hits[seen])))
    adjusted = adjusted_context(ctx, values, offsets, sky_tod if pixels is not None else None)
    return NominalFit(
        values=values,
        covariance=covariance,
        offsets_k=offsets,
        offset_sigmas_k=offset_sigmas,
        noise=noise,
        noise_covariance=noise_cov,
        sky_residual_tod=sky_tod if pixels is not None else None,
        sky_residual_rms_k=rms,
        sky_residual_noise_rms_k=noise_rms,
        sky_residual_nside=nside,
        sky_residual_pixels=pixels_used if subtracted else 0,
        context=adjusted,
        base=ctx,
        nuisance_lines_tod=line_tod,
    )


def refit_noise(ctx: Context, residual_f: np.ndarray, noise: list[NoiseModel]):
    """Whittle white + 1/f fit to each detector's residual (rfft, line bins excluded).

    Returns (models, covariances of (ln w, ln fk, alpha), change): ``change`` is the largest
    |ln S_new / S_old| at the frequencies where the effects' signals are (f_spin, 2 f_spin
    and n f_HWP, n = 1..6): how much their Delta chi^2 can move with the new weights.
    """
    n, fs = ctx.n_samples, ctx.sampling_rate_hz
    freqs = scipy.fft.rfftfreq(n, 1.0 / fs)
    quiet = np.ones(freqs.size, dtype=bool)
    quiet[0] = False
    if n % 2 == 0:
        quiet[-1] = False
    quiet &= ~line_exclusion_mask(freqs, ctx.f_hwp_hz, ctx.f_spin_hz, max(3 * fs / n, 2e-4))
    # below NOISE_FMIN_SPINS f_spin the sky, dipole and any slow drift of them live (e.g. a
    # gain drift times the dipole): fitted there, they would pass for a steep 1/f noise
    quiet &= freqs > NOISE_FMIN_SPINS * ctx.f_spin_hz
    models, covariances, change = [], [], 0.0
    for k in range(ctx.n_detectors):
        v = independent_fraction(ctx.valid[k])  # scales the periodogram, weights the modes
        power = residual_f[k].real ** 2 + residual_f[k].imag ** 2
        fitted = whittle_fit(freqs, power, quiet, periodogram_scale(n, fs, v), noise[k], v)
        models.append(fitted.model)
        covariances.append(fitted.covariance)
        where = np.array(
            [ctx.f_spin_hz, 2 * ctx.f_spin_hz] + [n * ctx.f_hwp_hz for n in range(1, 7)]
        )
        where = where[(where > 0) & (where < fs / 2)]
        ratio = fitted.model.psd(where) / noise[k].psd(where)
        change = max(change, float(np.max(np.abs(np.log(ratio)))))
    return models, covariances, change


def adjusted_context(ctx: Context, values: np.ndarray, offsets, sky_tod) -> Context:
    """The nominal model with the adjustments applied (a new :class:`Context`).

    A_2 cos x + c cos x + s sin x = A_2' cos(x - phi'), A_2' = |A_2 + c + i s|,
    phi' = atan2(s, A_2 + c); the other adjustments enter ``Context.adjustment``.
    """
    names = list(NOMINAL.parameters)
    v = {name: values[:, i] for i, name in enumerate(names)}
    templates = NOMINAL.templates(ctx)
    phase0 = np.zeros(ctx.n_detectors) if ctx.hwpss_phase_rad is None else ctx.hwpss_phase_rad
    a2 = np.hypot(ctx.a2_k + v["a2_cos"], v["a2_sin"])
    phase = phase0 + np.arctan2(v["a2_sin"], ctx.a2_k + v["a2_cos"])
    others = [i for i, name in enumerate(names) if name not in ("a2_cos", "a2_sin")]
    adjustment = np.einsum("kj,kjn->kn", values[:, others], templates[:, others])
    adjustment += np.asarray(offsets, dtype=float)[:, None]
    if sky_tod is not None:
        adjustment += sky_tod
    if ctx.adjustment is not None:
        adjustment += ctx.adjustment
    return dataclasses.replace(ctx, a2_k=a2, hwpss_phase_rad=phase, adjustment=adjustment)


def hwp_direction(ctx: Context) -> float:
    """+1 if chi increases with time, -1 otherwise."""
    chi = np.unwrap(ctx.hwp_angle_rad[: min(ctx.n_samples, 1000)])
    return 1.0 if chi[-1] >= chi[0] else -1.0


def adjustments_report(
    fit: NominalFit,
    corrections: dict[str, np.ndarray],
    correction_sigmas: dict[str, np.ndarray],
    nominal_noise: list[NoiseModel],
    pol_angles_rad: np.ndarray,
) -> dict:
    """{detector: {name: {value, sigma, unit, nominal}}}: the fitted nominal adjustments.

    ``corrections``/``correction_sigmas``: the adjustments refitted jointly with the
    selected effects (about the adjusted model, :mod:`.select`); their sigmas are the ones
    reported (marginalised over the effects).
    """
    ctx, base = fit.context, fit.base
    f_hwp = ctx.f_hwp_hz
    direction = hwp_direction(ctx)
    names = list(NOMINAL.parameters)
    out = {}
    for k, det in enumerate(ctx.detector_names):
        v = {name: fit.values[k, i] + corrections[name][k] for i, name in enumerate(names)}
        sig = {name: float(correction_sigmas[name][k]) for name in names}
        c, s = corrections["a2_cos"][k], corrections["a2_sin"][k]
        a2 = float(math.hypot(ctx.a2_k[k] + c, s))
        phase = float(ctx.hwpss_phase_rad[k] + math.atan2(s, ctx.a2_k[k] + c))
        lag = direction * phase
        tau_equivalent = math.tan(lag) / (2 * math.pi * 2 * f_hwp) if f_hwp > 0 else math.nan
        m, m0 = fit.noise[k], nominal_noise[k]
        w_sig, fk_sig, alpha_sig = (
            math.sqrt(max(fit.noise_covariance[k][i, i], 0.0))
            if np.isfinite(fit.noise_covariance[k][i, i])
            else math.nan
            for i in range(3)
        )
        out[det] = {
            "gain": {"value": 1.0 + v["gain"], "sigma": sig["gain"], "unit": "1", "nominal": 1.0},
            "offset": {
                "value": float(fit.offsets_k[k]),
                "sigma": float(fit.offset_sigmas_k[k]),
                "unit": "K",
                "nominal": 0.0,
            },
            "hwpss_2f_amplitude": {
                "value": a2,
                "sigma": sig["a2_cos"],
                "unit": "K",
                "nominal": float(base.a2_k[k]),
            },
            "hwpss_2f_phase": {
                "value": math.degrees(phase),
                "sigma": math.degrees(sig["a2_sin"] / a2) if a2 > 0 else math.nan,
                "unit": "deg",
                "nominal": 0.0,
                "equivalent_time_constant_s": tau_equivalent,
                "note": "phase of A_2 cos(2 (chi - theta_nominal) - phi): includes 2 x any "
                "polarisation-angle error; a time constant tau lags it by atan(2 pi 2 f_HWP tau)",
            },
            "pol_angle": {
                "value": math.degrees(float(pol_angles_rad[k]) + v["pol_angle"]),
                "sigma": math.degrees(sig["pol_angle"]),
                "unit": "deg",
                "nominal": math.degrees(float(pol_angles_rad[k])),
            },
            "sky_scale_intensity": {
                "value": 1.0 + v["sky_scale_intensity"],
                "sigma": sig["sky_scale_intensity"],
                "unit": "1",
                "nominal": 1.0,
            },
            "sky_scale_polarization": {
                "value": 1.0 + v["sky_scale_polarization"],
                "sigma": sig["sky_scale_polarization"],
                "unit": "1",
                "nominal": 1.0,
            },
            "sky_residual_rms": {
                "value": fit.sky_residual_rms_k,
                "sigma": fit.sky_residual_noise_rms_k,
                "unit": "K",
                "nominal": 0.0,
                "note": f"rms of the residual binned at nside {fit.sky_residual_nside} "
                f"({fit.sky_residual_pixels} pixels, both detectors); sigma = the rms white "
                "noise alone would give",
            },
            "noise_net": {
                "value": m.net_k_sqrt_s * 1e6,
                "sigma": m.net_k_sqrt_s * 1e6 * w_sig,
                "unit": "uK sqrt(s)",
                "nominal": m0.net_k_sqrt_s * 1e6,
            },
            "noise_fknee": {
                "value": m.fknee_hz * 1e3,
                "sigma": m.fknee_hz * 1e3 * fk_sig,
                "unit": "mHz",
                "nominal": m0.fknee_hz * 1e3,
            },
            "noise_alpha": {
                "value": m.alpha,
                "sigma": alpha_sig,
                "unit": "1",
                "nominal": m0.alpha,
            },
        }
    return out
