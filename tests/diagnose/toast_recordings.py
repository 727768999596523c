"""Recordings written by TOAST 3 (``toast.ops``), none of this package's simulator: a LiteBIRD
scan (``SimSatellite``: spin 20 min at 50 deg, precession 192.348 min at 45 deg, a HWP),
the sky map scanned by ``ScanHealpixMap`` through ``StokesWeights`` with the HWP, TOAST's
dipole (``SimDipole``, total) and noise (``DefaultNoiseModel`` + ``SimNoise``) and TOAST's
gain drift (``GainDrifter``), saved by ``SaveHDF5``.

The HWPSS and the nonlinearity have no TOAST operator; they are added to the observation's
signal here, as a TOAST user would: A_2 cos(2 (omega - gamma)) with omega the HWP angle and
gamma the focal plane's ``gamma``, then d -> (1 + g1 d) d.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import toast


def write_toast_recording(
    folder,
    sky_fits,
    hours: float,
    seed: int,
    coord: str = "G",
    n_pixels: int = 1,
    sample_rate_hz: float = 19.0,
    hwp_rpm: float = 39.0,
    a2_k: float = 0.0,
    g1_per_k: float = 0.0,
    gain_drift_sigma: float = 0.0,
    dipole: bool = True,
    noise: bool = True,
    net_uk_rts: float = 50.0,
    edit=None,
) -> Path:
    """Write one TOAST observation of ``2 n_pixels`` detectors; return the file's path.

    ``coord``: the frame of SimSatellite's pointing, which must be the sky map's
    (ScanHealpixMap does not rotate): G for the Galactic maps the diagnosis is given.
    ``edit(data)``: called on the toast.Data just before it is saved."""
    import astropy.units as u
    from toast import ops
    from toast.instrument import SpaceSite, Telescope
    from toast.instrument_sim import fake_hexagon_focalplane
    from toast.observation import default_values as defaults
    from toast.schedule_sim_satellite import create_satellite_schedule

    rate = sample_rate_hz * u.Hz
    focalplane = fake_hexagon_focalplane(
        n_pix=n_pixels,
        sample_rate=rate,
        psd_fmin=1e-5 * u.Hz,
        psd_net=net_uk_rts * 1e-6 * u.K * np.sqrt(1 * u.s),
        psd_fknee=20e-3 * u.Hz,
        width=5 * u.deg,
        bandcenter=140 * u.GHz,
        fwhm=30 * u.arcmin,
    )
    telescope = Telescope("litebird", focalplane=focalplane, site=SpaceSite("L2"))
    schedule = create_satellite_schedule(
        prefix="obs_",
        mission_start=datetime(2032, 4, 1, tzinfo=UTC),
        observation_time=hours * u.hour,
        gap_time=0 * u.minute,
        num_observations=1,
        prec_period=192.348 * u.minute,
        spin_period=20 * u.minute,
    )
    data = toast.Data(toast.Comm())
    ops.SimSatellite(
        name="satellite",
        telescope=telescope,
        schedule=schedule,
        hwp_angle=defaults.hwp_angle,
        hwp_rpm=hwp_rpm,
        spin_angle=50 * u.deg,
        prec_angle=45 * u.deg,
        coord=coord,
    ).apply(data)
    pointing = ops.PointingDetectorSimple(boresight=defaults.boresight_radec)
    pixels = ops.PixelsHealpix(nside=_nside(sky_fits), detector_pointing=pointing)
    weights = ops.StokesWeights(
        mode="IQU", hwp_angle=defaults.hwp_angle, detector_pointing=pointing
    )
    ops.ScanHealpixMap(file=str(sky_fits), pixel_pointing=pixels, stokes_weights=weights).apply(
        data
    )
    if dipole:
        ops.SimDipole(mode="total", coord=coord, detector_pointing=pointing).apply(data)
    observation = data.obs[0]
    signal = observation.detdata[defaults.det_data]
    hwp = np.asarray(observation.shared[defaults.hwp_angle].data)
    for k, name in enumerate(observation.local_detectors):
        gamma = focalplane[name]["gamma"].to_value(u.rad)
        total = signal[name] + a2_k * np.cos(2 * (hwp - gamma))
        signal[name][:] = (1 + g1_per_k * total) * total
    if gain_drift_sigma:
        ops.GainDrifter(
            drift_mode="linear_drift", sigma_drift=gain_drift_sigma, realization=seed
        ).apply(data)
    if noise:
        ops.DefaultNoiseModel().apply(data)
        ops.SimNoise(realization=seed).apply(data)
    ops.Delete(detdata=[pixels.pixels, weights.weights, pointing.quats]).apply(data)
    if edit is not None:
        edit(data)
    folder = Path(folder)
    ops.SaveHDF5(volume=str(folder)).apply(data)
    return next(folder.glob("obs_*.h5"))


def _nside(sky_fits) -> int:
    import healpy as hp

    return hp.get_nside(hp.read_map(str(sky_fits), field=0, dtype=np.float64))
