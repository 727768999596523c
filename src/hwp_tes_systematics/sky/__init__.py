"""Input sky: CMB realisations from the PTEP spectra and d0s0-like foregrounds via pysm3.

Conventions (the whole package): HEALPix RING maps in Galactic coordinates, shape
``(3, npix)`` = (I, Q, U), in K_CMB (thermodynamic temperature of the CMB black body,
T_CMB = 2.7255 K), a_lm in healpy ordering (``hp.Alm.getidx``), angular power spectra
C_ell (not D_ell = ell (ell + 1) C_ell / 2 pi) in K_CMB^2, ordered (TT, EE, BB, TE).

Submodules (each with its own description, constants and sources):

* :mod:`.conventions`: map unit (K_CMB), number of Stokes parameters, polarisation
  convention (COSMO);
* :mod:`.cmb`: the PTEP CMB spectra shipped in litebird_sim, Gaussian a_lm, the Gaussian
  beam (:func:`smooth_alm`) and CMB realisation maps;
* :mod:`.templates`: the EMBEDDED OFFLINE foreground templates (NOT pysm3 data), power-law
  Gaussian fields times a Galactic-latitude envelope, with their constants;
* :mod:`.foregrounds`: the d0/s0 SEDs, the choice between pysm3 data and the offline
  templates, pysm3 bandpass integration and conversion to K_CMB, foreground maps;
* :mod:`.channels`: the sky seen by one channel (CMB + foreground, beam-smoothed);
* :mod:`.fits_io`: FITS writing and reading of sky maps (header keys, IAU input);
* :mod:`.harmonics`: I, Q, U <-> T, E, B transforms with ducc0's SHT, as healpy's
  ``alm2map`` and ``map2alm`` (used as ``sky.harmonics.alm2map``: not re-exported).

Imports between them go one way: conventions <- cmb <- templates <- foregrounds <-
channels, and conventions <- fits_io. Every name is re-exported here, so
``from hwp_tes_systematics import sky; sky.cmb_map(...)`` is the way to use them.
"""

from .channels import channel_sky_map
from .cmb import (
    CMB_SCALAR_FILE,
    CMB_TENSOR_FILE,
    SPECTRA_ORDER,
    UK2_TO_K2,
    beam_band_limit,
    cmb_alm,
    cmb_map,
    cmb_spectra,
    gaussian_alm,
    lensing_bb,
    smooth_alm,
    tensor_bb_r1,
)
from .conventions import MAP_UNIT, N_STOKES, POLARISATION_CONVENTION
from .fits_io import (
    FOREGROUND_SOURCE_KEY,
    map_metadata,
    read_sky_header,
    read_sky_map,
    write_sky_map,
)
from .foregrounds import (
    DUST_BETA,
    DUST_TEMPERATURE_K,
    OFFLINE_SOURCE,
    PYSM_PRESETS,
    PYSM_SOURCE,
    SYNC_BETA,
    ForegroundModels,
    band_factors,
    foreground_emission,
    foreground_map,
    foreground_models,
    foreground_source,
    pysm_bandpass,
)
from .foregrounds import _foreground_models as _foreground_models  # its cache, cleared in tests
from .templates import (
    COMPONENTS,
    DUST_ALPHA_BB,
    DUST_ALPHA_EE,
    DUST_ALPHA_TT,
    DUST_BB_OVER_EE,
    DUST_D80_EE_UK_CMB2,
    DUST_FREQ_REF_GHZ,
    DUST_I_POLE_UK_RJ,
    DUST_PLANE_CORE_DEG,
    DUST_R_TE,
    ELL_MAX_RMS,
    ELL_PIVOT,
    INTENSITY_FLOOR_FRACTION,
    INTENSITY_RMS_FRACTION,
    SYNC_ALPHA_BB,
    SYNC_ALPHA_EE,
    SYNC_ALPHA_TT,
    SYNC_BB_OVER_EE,
    SYNC_D80_EE_UK_RJ2,
    SYNC_FREQ_REF_GHZ,
    SYNC_I_POLE_UK_RJ,
    SYNC_PLANE_CORE_DEG,
    SYNC_R_TE,
    galactic_envelope,
    offline_template_spectra,
    offline_templates,
    power_law_spectra,
)

__all__ = [
    "CMB_SCALAR_FILE",
    "CMB_TENSOR_FILE",
    "COMPONENTS",
    "DUST_ALPHA_BB",
    "DUST_ALPHA_EE",
    "DUST_ALPHA_TT",
    "DUST_BB_OVER_EE",
    "DUST_BETA",
    "DUST_D80_EE_UK_CMB2",
    "DUST_FREQ_REF_GHZ",
    "DUST_I_POLE_UK_RJ",
    "DUST_PLANE_CORE_DEG",
    "DUST_R_TE",
    "DUST_TEMPERATURE_K",
    "ELL_MAX_RMS",
    "ELL_PIVOT",
    "FOREGROUND_SOURCE_KEY",
    "INTENSITY_FLOOR_FRACTION",
    "INTENSITY_RMS_FRACTION",
    "MAP_UNIT",
    "N_STOKES",
    "OFFLINE_SOURCE",
    "POLARISATION_CONVENTION",
    "PYSM_PRESETS",
    "PYSM_SOURCE",
    "SPECTRA_ORDER",
    "SYNC_ALPHA_BB",
    "SYNC_ALPHA_EE",
    "SYNC_ALPHA_TT",
    "SYNC_BB_OVER_EE",
    "SYNC_BETA",
    "SYNC_D80_EE_UK_RJ2",
    "SYNC_FREQ_REF_GHZ",
    "SYNC_I_POLE_UK_RJ",
    "SYNC_PLANE_CORE_DEG",
    "SYNC_R_TE",
    "UK2_TO_K2",
    "ForegroundModels",
    "band_factors",
    "beam_band_limit",
    "channel_sky_map",
    "cmb_alm",
    "cmb_map",
    "cmb_spectra",
    "foreground_emission",
    "foreground_map",
    "foreground_models",
    "foreground_source",
    "galactic_envelope",
    "gaussian_alm",
    "lensing_bb",
    "map_metadata",
    "offline_template_spectra",
    "offline_templates",
    "power_law_spectra",
    "pysm_bandpass",
    "read_sky_header",
    "read_sky_map",
    "smooth_alm",
    "tensor_bb_r1",
    "write_sky_map",
]
