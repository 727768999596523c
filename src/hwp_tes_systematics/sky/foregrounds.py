"""d0s0-like foregrounds via pysm3: SED scaling and bandpass integration of the templates.

Two components with the SEDs of the pysm3 presets d0 and s0 (constant spectral
parameters over the sky): modified black body dust, beta_d = 1.54, T_d = 20 K, and
power-law synchrotron, beta_s = -3, in Rayleigh-Jeans brightness temperature:

    T_RJ^dust(nu) = T_RJ^dust(nu_0) (nu / nu_0)^(beta_d - 2) B_nu(T_d) / B_nu0(T_d)
    T_RJ^sync(nu) = T_RJ^sync(nu_0) (nu / nu_0)^beta_s

The templates T(nu_0) are either

* the pysm3 d0/s0 template files (``pysm_2/dust_{t,q,u}_new.fits``, I at 545 GHz and
  Q, U at 353 GHz; ``pysm_2/synch_{t,q,u}_new.fits``, I at 408 MHz and Q, U at 23 GHz)
  when a local pysm3 data folder is given (argument ``pysm_local_data`` or environment
  variable ``PYSM_LOCAL_DATA``); nothing is ever downloaded: missing files raise
  :class:`FileNotFoundError`; or
* EMBEDDED OFFLINE templates (flag :data:`OFFLINE_SOURCE`, "NOT pysm3 data"):
  Gaussian random fields with power-law angular spectra (constants and their sources
  in :mod:`~hwp_tes_systematics.sky.templates`) times a smooth Galactic-latitude
  envelope, fixed for a master seed and nside.

In both cases pysm3 models (``ModifiedBlackBody``, ``PowerLaw``) do the SED scaling and
the bandpass integration, and ``pysm3.bandpass_unit_conversion`` the conversion to
K_CMB. pysm3 bandpass weights multiply the specific intensity I_nu (W m^-2 Hz^-1 sr^-1).
A single-mode, single-polarisation detector of transmission w(nu) receives
P = integral w(nu) (c^2 / 2 nu^2) I_nu d nu (see :mod:`radiometry`), so the pysm3
weights are w(nu) / nu^2 (``single_mode=True``, the default). The map then holds

    T_CMB-equivalent = integral w T_RJ d nu / integral w (dT_RJ / dT_CMB) d nu,

exactly the temperature whose power is dP/dT x T with the dP/dT of
:func:`radiometry.dpower_dtemperature_w_per_k`. ``single_mode=False`` passes w(nu)
unchanged (the pysm3 / litebird_sim convention of a constant-etendue detector).

With constant spectral parameters the band-integrated emission is the template times
one factor per Stokes parameter; the factors are obtained by evaluating the same pysm3
model on unit templates, which is exact and avoids integrating all pixels at the 2001
samples of a band (checked against the full-map pysm3 evaluation in the tests).
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import healpy as hp
import numpy as np

from ..instrument.radiometry import Bandpass
from .cmb import _check_fwhm, _check_nside, smooth_alm
from .conventions import MAP_UNIT, N_STOKES
from .templates import COMPONENTS, DUST_FREQ_REF_GHZ, SYNC_FREQ_REF_GHZ, offline_templates

log = logging.getLogger(__package__)  # "hwp_tes_systematics.sky", as before the split

# pysm3 presets d0 / s0 (pysm3/data/presets.cfg): beta_d = 1.54, T_d = 20 K, beta_s = -3.
DUST_BETA = 1.54
DUST_TEMPERATURE_K = 20.0
SYNC_BETA = -3.0

PYSM_SOURCE = "pysm3 d0s0 templates"
OFFLINE_SOURCE = "embedded offline power-law templates (NOT pysm3 data)"
PYSM_PRESETS = {"dust": "d0", "synchrotron": "s0"}


def _pysm_folder(pysm_local_data) -> str | None:
    """The pysm3 data folder: the argument, else $PYSM_LOCAL_DATA, else None (offline)."""
    if pysm_local_data is not None and str(pysm_local_data) != "":
        return str(pysm_local_data)
    env = os.environ.get("PYSM_LOCAL_DATA", "")
    return env or None


def _pysm_component_config(folder: str) -> dict[str, dict]:
    """The d0 and s0 preset configurations with their template files made absolute.

    Raises FileNotFoundError naming the first missing file (nothing is downloaded).
    """
    from pysm3.sky import PRESET_MODELS

    configs = {}
    for component, preset in PYSM_PRESETS.items():
        config = dict(PRESET_MODELS[preset])
        for key, value in config.items():
            if key.startswith("map_") and isinstance(value, str):
                path = Path(folder) / value
                if not path.is_file():
                    raise FileNotFoundError(
                        f"pysm3 template {path} (preset {preset} {key}, {component}) not found "
                        f"in pysm_local_data = {folder!r}: put the pysm3 data there (folder "
                        "holding pysm_2/) or leave pysm_local_data and $PYSM_LOCAL_DATA unset "
                        "for the embedded offline templates; nothing is downloaded"
                    )
                config[key] = str(path)
        configs[preset] = config
    return configs


def foreground_source(pysm_local_data=None) -> str:
    """Which foreground templates are used: :data:`PYSM_SOURCE` or :data:`OFFLINE_SOURCE`.

    pysm3 data are used if ``pysm_local_data`` (or $PYSM_LOCAL_DATA) is set; then all the
    d0/s0 template files must exist there (FileNotFoundError naming the missing one).
    """
    folder = _pysm_folder(pysm_local_data)
    if folder is None:
        return OFFLINE_SOURCE
    _pysm_component_config(folder)
    return PYSM_SOURCE


@dataclass(frozen=True, eq=False)
class ForegroundModels:
    """pysm3 models of the two components at one nside and where their templates come from."""

    source: str
    nside: int
    models: dict = field(repr=False)  # {"dust": pysm3 Model, "synchrotron": pysm3 Model}

    def template(self, component: str) -> np.ndarray:
        """(3, npix) reference template I Q U [uK_RJ] of a component (float64 copy)."""
        import pysm3.units as u

        model = self.models[component]
        return np.array(
            [np.asarray(model.I_ref.to_value(u.uK_RJ), dtype=float)]
            + [np.asarray(getattr(model, f"{s}_ref").to_value(u.uK_RJ), float) for s in "QU"]
        )


@functools.lru_cache(maxsize=4)
def _foreground_models(nside: int, master_seed: int | None, folder: str | None):
    import pysm3
    import pysm3.units as u

    if folder is not None:
        config = _pysm_component_config(folder)
        sky = pysm3.Sky(nside=nside, component_config=config, output_unit=MAP_UNIT)
        models = dict(zip(PYSM_PRESETS, sky.components))
        return ForegroundModels(source=PYSM_SOURCE, nside=nside, models=models)

    log.warning(
        "foregrounds: no pysm3 data (pysm_local_data / $PYSM_LOCAL_DATA unset); using %s",
        OFFLINE_SOURCE,
    )
    templates = offline_templates(nside, master_seed)

    def quantities(component):
        return [u.Quantity(templates[component][i], u.uK_RJ, copy=True) for i in range(3)]

    dust_i, dust_q, dust_u = quantities("dust")
    sync_i, sync_q, sync_u = quantities("synchrotron")
    models = {
        "dust": pysm3.models.ModifiedBlackBody(
            map_I=dust_i,
            map_Q=dust_q,
            map_U=dust_u,
            freq_ref_I=f"{DUST_FREQ_REF_GHZ} GHz",
            freq_ref_P=f"{DUST_FREQ_REF_GHZ} GHz",
            map_mbb_index=DUST_BETA,
            map_mbb_temperature=DUST_TEMPERATURE_K,
            unit_mbb_temperature="K",
            nside=nside,
        ),
        "synchrotron": pysm3.models.PowerLaw(
            map_I=sync_i,
            map_Q=sync_q,
            map_U=sync_u,
            freq_ref_I=f"{SYNC_FREQ_REF_GHZ} GHz",
            freq_ref_P=f"{SYNC_FREQ_REF_GHZ} GHz",
            map_pl_index=SYNC_BETA,
            nside=nside,
        ),
    }
    return ForegroundModels(source=OFFLINE_SOURCE, nside=nside, models=models)


def foreground_models(nside: int, master_seed: int, pysm_local_data=None) -> ForegroundModels:
    """pysm3 dust (d0-like) and synchrotron (s0-like) models at ``nside`` (cached).

    pysm3 data if available (see :func:`foreground_source`), else the offline templates
    of :func:`offline_templates` fed in memory to ``pysm3.models.ModifiedBlackBody``
    (353 GHz, beta_d, T_d) and ``pysm3.models.PowerLaw`` (23 GHz, beta_s).
    """
    nside = _check_nside(nside)
    folder = _pysm_folder(pysm_local_data)
    if folder is not None:
        folder = str(Path(folder).resolve())
        return _foreground_models(nside, None, folder)
    return _foreground_models(nside, int(master_seed), None)


def pysm_bandpass(bandpass: Bandpass, single_mode: bool = True):
    """(frequencies as a Quantity in GHz, pysm3 weights) of a band; samples at nu <= 0 dropped.

    pysm3 weights multiply I_nu; a single-mode detector of transmission w(nu) weighs
    I_nu by w(nu) c^2 / (2 nu^2), hence weights w / nu^2 (any constant factor drops out).
    """
    import pysm3.units as u

    freqs = np.asarray(bandpass.freqs_ghz, dtype=float)
    weights = np.asarray(bandpass.weights, dtype=float)
    keep = freqs > 0
    freqs, weights = freqs[keep], weights[keep]
    if freqs.size == 0 or np.trapezoid(weights, freqs) <= 0:
        raise ValueError("bandpass: expected positive frequencies and a positive integral")
    if single_mode:
        weights = weights / freqs**2
    return freqs * u.GHz, weights


def _unit_twin(model):
    """The same pysm3 model (class, reference frequencies, spectral parameters) on
    unit templates (12 pixels of 1 uK_RJ), for its band-integrated SED factors."""
    import pysm3
    import pysm3.units as u

    one = [np.ones(12) * u.uK_RJ for _ in range(3)]
    if type(model) is pysm3.models.ModifiedBlackBody:
        index, temperature = model.mbb_index, model.mbb_temperature.to(u.K)
        if np.ndim(index) or np.ndim(temperature):
            raise ValueError("ModifiedBlackBody with spatially varying beta / T: not d0-like")
        return pysm3.models.ModifiedBlackBody(
            map_I=one[0],
            map_Q=one[1],
            map_U=one[2],
            freq_ref_I=model.freq_ref_I,
            freq_ref_P=model.freq_ref_P,
            map_mbb_index=float(index.value),
            map_mbb_temperature=float(temperature.value),
            unit_mbb_temperature="K",
            nside=1,
        )
    if type(model) is pysm3.models.PowerLaw:
        if np.ndim(model.pl_index):
            raise ValueError("PowerLaw with a spatially varying index: not s0-like")
        return pysm3.models.PowerLaw(
            map_I=one[0],
            map_Q=one[1],
            map_U=one[2],
            freq_ref_I=model.freq_ref_I,
            freq_ref_P=model.freq_ref_P,
            map_pl_index=float(model.pl_index.value),
            nside=1,
        )
    raise TypeError(f"{type(model).__name__}: only ModifiedBlackBody and PowerLaw are supported")


def band_factors(model, bandpass: Bandpass, unit: str = MAP_UNIT, single_mode: bool = True):
    """(3,) band-integrated emission per uK_RJ of reference template, I Q U, in ``unit``.

    pysm3 evaluates the model's SED on unit templates with ``get_emission(freqs, weights)``
    [uK_RJ] and ``bandpass_unit_conversion(freqs, weights, unit)`` converts to ``unit``
    (factor in unit / uK_RJ; cut = 0 so both see the same samples).
    """
    import pysm3
    import pysm3.units as u

    freqs, weights = pysm_bandpass(bandpass, single_mode)
    emission = _unit_twin(model).get_emission(freqs, weights)[:, 0]
    factor = pysm3.bandpass_unit_conversion(freqs, weights, u.Unit(unit), cut=0.0)
    return np.asarray((emission * factor).to_value(u.Unit(unit)), dtype=float)


def _components(components) -> tuple[str, ...]:
    components = COMPONENTS if components is None else tuple(components)
    unknown = set(components) - set(COMPONENTS)
    if unknown:
        raise ValueError(f"components {sorted(unknown)}: expected a subset of {COMPONENTS}")
    return components


def foreground_emission(
    bandpass: Bandpass,
    nside: int,
    master_seed: int,
    pysm_local_data=None,
    unit: str = MAP_UNIT,
    components=None,
    single_mode: bool = True,
) -> np.ndarray:
    """Band-integrated foreground (3, npix) I Q U in ``unit`` (default K_CMB), unsmoothed.

    Sum over ``components`` (default dust and synchrotron) of template x band factor.
    """
    fg = foreground_models(nside, master_seed, pysm_local_data)
    total = np.zeros((N_STOKES, hp.nside2npix(fg.nside)))
    for component in _components(components):
        factors = band_factors(fg.models[component], bandpass, unit, single_mode)
        total += factors[:, None] * fg.template(component)
    return total


@functools.lru_cache(maxsize=4)
def _template_alms(fg: ForegroundModels, component: str) -> np.ndarray:
    """T E B a_lm of a template at lmax = 3 nside - 1 (healpy map2alm, 3 iterations)."""
    alm = hp.map2alm(fg.template(component), lmax=3 * fg.nside - 1, pol=True, iter=3)
    alm.flags.writeable = False
    return alm


def foreground_map(
    bandpass: Bandpass,
    nside: int,
    master_seed: int,
    fwhm_arcmin: float,
    pysm_local_data=None,
    lmax: int | None = None,
    components=None,
    single_mode: bool = True,
) -> np.ndarray:
    """Band-integrated foreground (3, npix) I Q U [K_CMB], smoothed with a Gaussian beam.

    K_CMB map = sum_c f_c(band) x template_c (see :func:`band_factors`), then the beam
    (:func:`smooth_alm`) is applied in harmonic space up to ``lmax`` (default
    3 nside - 1) without pixel window; ``fwhm_arcmin = 0`` returns the unsmoothed map.
    With constant spectral parameters I scales with f_I and (Q, U), hence (E, B), with
    f_P, so the template a_lm (cached) are scaled instead of the maps. The template
    source is given by :func:`foreground_source` (pysm3 data or offline templates).
    """
    fwhm_arcmin = _check_fwhm(fwhm_arcmin)
    if fwhm_arcmin == 0:
        return foreground_emission(
            bandpass, nside, master_seed, pysm_local_data, MAP_UNIT, components, single_mode
        )
    fg = foreground_models(nside, master_seed, pysm_local_data)
    lmax = 3 * fg.nside - 1 if lmax is None else int(lmax)
    if not 0 <= lmax <= 3 * fg.nside - 1:
        raise ValueError(f"lmax = {lmax}: expected 0 <= lmax <= 3 nside - 1 = {3 * fg.nside - 1}")
    alm = None
    for component in _components(components):
        factors = band_factors(fg.models[component], bandpass, MAP_UNIT, single_mode)
        scaled = _template_alms(fg, component) * factors[:, None]
        alm = scaled if alm is None else alm + scaled
    if alm is None:
        return np.zeros((N_STOKES, hp.nside2npix(fg.nside)))
    alm = np.array([hp.resize_alm(a, 3 * fg.nside - 1, 3 * fg.nside - 1, lmax, lmax) for a in alm])
    alm = smooth_alm(alm, fwhm_arcmin, lmax)
    return hp.alm2map(alm, fg.nside, lmax=lmax, pixwin=False)
