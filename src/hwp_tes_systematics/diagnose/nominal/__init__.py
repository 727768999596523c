"""Step 1, the nominal fit: d_nom of the recording (:mod:`..model`) and its adjustments
(gain, offset, 2f amplitude and phase, polarisation angle, sky scales, noise; fitted, never
effects: :mod:`.adjustments`), as a :class:`NominalFit` (:mod:`.step`)."""

from .adjustments import NOMINAL, SKY_RESIDUAL_NSIDE, adjustments_report, fit_nominal, refit_noise
from .step import NominalFit, fit_nominal_model

__all__ = [
    "NOMINAL",
    "SKY_RESIDUAL_NSIDE",
    "NominalFit",
    "adjustments_report",
    "fit_nominal",
    "fit_nominal_model",
    "refit_noise",
]
