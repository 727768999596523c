"""Step 1 of the diagnosis: the recording against its adjusted simulation (:class:`NominalFit`)."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from ..effects import noise_effect
from ..fourier import rfft
from ..model import build_context, load_sky, per_detector
from ..noise import NoiseModel, estimate_noise, fitted_modes
from ..recording import Recording
from .adjustments import fit_nominal

log = logging.getLogger(__name__)


@dataclasses.dataclass
class NominalFit:
    """Step 1 (:func:`fit_nominal_model`): the recording against its adjusted simulation."""

    recording: Recording
    sky_source: str  # where the sky came from (a path, or "array")
    a2_k: np.ndarray  # (n_det,) nominal A_2 [K]
    nominal: list[NoiseModel]  # the configured noise, or the recording's estimate
    estimates: list  # the noise estimated on the first residual (noise.NoiseEstimate)
    adjusted: object  # nominal.fit_nominal's result (its noise follows the later steps)
    noise_models: list  # the noise the fit weighs with (a pole added if it rolls off)
    residual: np.ndarray  # (n_det, n_samples) recording - adjusted d_nom [K], 0 where invalid
    residual_f: np.ndarray  # its real FFT

    @property
    def context(self):
        """The adjusted model's :class:`.model.Context`."""
        return self.adjusted.context


def fit_nominal_model(
    recording: Recording,
    sky_iqu,
    a2_k,
    nominal_noise,
    sky_residual_nside,
    delta_bic_threshold: float,
    workers: int,
) -> NominalFit:
    """Step 1: d_nom of the recording, the noise estimated on its residual where none is
    configured, the nominal adjustments fitted (gain, 2f amplitude and phase, polarisation
    angle, sky scales, offsets, sky residual, noise: never effects), and the noise's
    roll-off (:mod:`.rolloff`) taken into the noise model if it lowers the BIC by more than
    ``delta_bic_threshold`` (white + 1/f alone would pass it for a ~1 Hz knee)."""
    sky, sky_source = load_sky(sky_iqu)
    a2 = per_detector(a2_k, recording.n_detectors, "a2_k")
    nominal = _nominal_noise_models(recording, nominal_noise)
    base = build_context(recording, sky, a2)
    residual0 = np.where(base.valid, recording.tod - base.d_nom, 0.0)
    estimates = [
        estimate_noise(
            residual0[k],
            base.sampling_rate_hz,
            base.valid[k],
            base.f_hwp_hz,
            base.f_spin_hz,
            nominal[k].fmin_hz if nominal[k] is not None else 1e-5,
            start=nominal[k],
        )
        for k in range(base.n_detectors)
    ]
    nominal = [m if m is not None else e.model for m, e in zip(nominal, estimates, strict=True)]
    adjusted = fit_nominal(
        base,
        recording.tod,
        nominal,
        sky_residual_nside=sky_residual_nside,
        workers=workers,
    )
    ctx = adjusted.context
    noise_models = adjusted.noise
    residual = np.where(ctx.valid, recording.tod - ctx.d_nom, 0.0)
    modes = fitted_modes(residual.shape[1])
    residual_f = rfft(residual, axis=-1, workers=workers)  # locate's and FitProblem's too
    ln_n_eff = math.log(2 * modes.sum() * ctx.n_detectors)
    # fitted before any effect, on the residual without the HWP lines: a strong line (the
    # 4f of a nonlinearity, 21 mK on H3-402 at g1 = 3e-3) cut by a gap leaks over the whole
    # band and passed for a pole of 27 ms, which corrupted every later noise fit
    line_free_f = residual_f - rfft(adjusted.nuisance_lines_tod, axis=-1, workers=workers)
    early = noise_effect("rolloff").fit_noise(ctx, line_free_f, noise_models, modes, ln_n_eff)
    if early.delta_bic < delta_bic_threshold and not _sidebands_fit_better(
        ctx, early, line_free_f, noise_models, modes, ln_n_eff
    ):
        noise_models = adjusted.noise = early.noise
    return NominalFit(
        recording, sky_source, a2, nominal, estimates, adjusted, noise_models, residual, residual_f
    )


def _nominal_noise_models(recording: Recording, nominal_noise) -> list[NoiseModel]:
    """Noise per detector: from ``nominal_noise`` or the recording's detector metadata.

    ``nominal_noise``: None, (net_ukrts, fknee_mhz, alpha[, fmin_hz]), a dict with those
    keys, a NoiseModel, or a list of one of these per detector.
    """
    n_det = recording.n_detectors
    metadata = recording.nominal_noise()
    if nominal_noise is None:
        items = [None] * n_det
    elif (
        isinstance(nominal_noise, list)
        and len(nominal_noise) == n_det
        and not all(isinstance(x, (int, float)) for x in nominal_noise)
    ):
        items = list(nominal_noise)
    else:
        items = [nominal_noise] * n_det
    models = []
    for k, item in enumerate(items):
        meta = metadata[k]
        if item is None:
            values = meta
        elif isinstance(item, NoiseModel):
            models.append(item)
            continue
        elif isinstance(item, dict):
            values = {**meta, **item}
        else:
            item = tuple(item)
            if len(item) not in (3, 4):
                raise ValueError(
                    f"nominal_noise = {nominal_noise!r}: expected (net_ukrts, fknee_mhz, alpha"
                    "[, fmin_hz])"
                )
            values = dict(meta)
            values.update(zip(("net_ukrts", "fknee_mhz", "alpha", "fmin_hz"), item, strict=False))
        if not (math.isfinite(values["net_ukrts"]) and values["net_ukrts"] > 0):
            # no NET in the file (a lab detector): the noise is a nominal adjustment
            # anyway; it starts from a robust estimate on the residual (see diagnose)
            log.warning(
                "%s: no NET for detector %r in the file: the noise starts from the residual",
                recording.source,
                recording.detector_names[k],
            )
            models.append(None)
            continue
        models.append(NoiseModel.from_detector(values))
    return models


def _sidebands_fit_better(ctx, early, residual_f, noise_models, modes, ln_n_eff) -> bool:
    """Whether a gain fluctuation's 2f sidebands (:mod:`.fluctuations`) explain the residual
    better in BIC than the early roll-off does: their wings fall away from 2 f_HWP as a
    pole rolls the noise off, and a pole taken for them (up to its bound, ~46 ms, with the
    white level collapsing beneath) corrupts every later noise fit. The fluctuation itself
    is tested after the effects are fitted; here it only stops the pole."""
    sidebands = noise_effect("excess").fit_noise(ctx, residual_f, noise_models, modes, ln_n_eff)
    return sidebands.delta_bic < early.delta_bic
