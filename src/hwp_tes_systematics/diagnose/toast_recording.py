"""Recordings from TOAST 3: an observation file written by ``toast.ops.SaveHDF5``, read as a
:class:`.recording.Recording` with the nominal model of the diagnosis.

What is read (TOAST 3 HDF5 format, ``toast_format_version`` 1 or 2), with h5py and astropy:

* ``shared/times`` (unix seconds, UTC): the start time and the sampling rate;
* ``shared/boresight_radec`` (or the one ``shared/boresight_*``), (n, 4) quaternions
  (x, y, z, w), and ``instrument/focalplane``'s ``quat``: each detector's pointing is
  R_boresight R_detector, turned into ecliptic (theta, phi, psi) (litebird_sim's angles,
  :func:`.simulation.data_model.quaternion_pointing`);
* ``shared/hwp_angle`` [rad]: a recording without it is refused (the diagnosis is of a
  rotating HWP);
* ``detdata/signal`` (units from its ``units`` attribute, K_CMB assumed for K) and
  ``detdata/flags`` & 7, ``shared/flags`` & 15 (TOAST's non-science masks); a detector whose
  observation flag (``observation_detector_flags``) has bit 1 set is left out;
* ``shared/position`` and ``shared/velocity`` (km, km/s): the pointing's frame and the
  spacecraft's velocity for the orbital dipole.
* the focal plane's ``wafer``, ``squid`` and ``pixel`` columns, where it has them: the
  detectors' groups (:attr:`.recording.Recording.groups`).

The pointing's frame is not written in the file. It is found from the spacecraft: the
recorded position and velocity are compared with the Earth's (astropy's built-in
ephemeris) in equatorial (C), ecliptic (E) and Galactic (G) coordinates, the frames TOAST's
``SimSatellite(coord=...)`` offers; one must agree within FRAME_TOLERANCE_DEG and the next
differ by more than FRAME_SEPARATION_DEG, else the file is refused.

Polarisation. TOAST's ``StokesWeights`` with a HWP (COSMO convention) gives, with eta the
polarisation efficiency, alpha_T the detector orientation, omega the HWP angle and gamma
the focal plane's ``gamma``,

    d = I + eta [Q cos 2b + U sin 2b],   2b = 2 alpha_T - 4 (gamma - omega)   (mod 2 pi),

and alpha_T = psi + pi / 2 for the full detector quaternion's litebird_sim orientation psi.
The nominal model's 2 a = 4 chi + 2 psi - 2 theta_k is the same signal for

    chi = omega,   psi = the detector's own psi,   theta_k = 2 gamma - pi / 2,
    rho_k = (1 - epsilon) / (1 + epsilon),  epsilon = the ``pol_leakage`` column,

checked against TOAST's own scan of a map (tests/diagnose/test_toast_recording.py).
The nominal 2f HWPSS phase 2 (chi - theta_k) follows from theta_k; a TOAST recording
has no HWPSS unless its maker added one (give ``--a2`` accordingly).

The dipole: litebird_sim's (``TOTAL_FROM_LIN_T``, its solar velocity) with the
spacecraft velocity the file carries, rotated to ecliptic. TOAST's ``SimDipole`` uses
another solar velocity (370.08 against 369.82 km/s) and its own Doppler formula: at most
1.5 uK apart on a 3 mK dipole (measured, tests/diagnose/test_toast_recording.py), a
difference fixed on the sky that the nominal adjustments absorb.

Why h5py rather than ``toast.io.load_hdf5``: TOAST 3.0.6 cannot load a file whose
observation has no plain metadata (``metadata/other`` without ``python_data_type``),
which is what ``SimSatellite`` writes; reading the datasets needs nothing of TOAST.
Detector data compressed by SaveHDF5 (FLAC) are decoded with ``flacarray``, installed
with TOAST (``pip install hwp_tes_systematics[toast]``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import astropy.time
import numpy as np

from .recording import GROUP_KEYS, Recording, mask_bad_samples
from .recording_checks import MIN_SAMPLES, check_memory, fail

DET_MASK_NONSCIENCE = 7  # toast.observation.default_values.det_mask_nonscience
SHARED_MASK_NONSCIENCE = 15  # ... shared_mask_nonscience
DET_MASK_INVALID = 1  # ... det_mask_invalid (observation_detector_flags)
FRAME_TOLERANCE_DEG = 1.0
FRAME_SEPARATION_DEG = 3.0
ORBIT_STEP_S = 60.0  # spacing of the velocity table handed to litebird_sim's dipole


def _decode(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _dataset(path, handle, name: str, shape_tail=()):
    """``handle[name]``: a shared dataset of shape (n_samples, *shape_tail), or detdata."""
    import h5py

    if name not in handle:
        group, _, _ = name.rpartition("/")
        present = sorted(handle[group]) if group in handle else []
        fail(path, f"TOAST observation without {name!r} (the group holds {present})")
    item = handle[name]
    if not isinstance(item, h5py.Dataset) and not name.startswith("detdata/"):
        fail(path, f"{name!r} is not a dataset")
    if name.startswith("shared/") and tuple(item.shape[1:]) != tuple(shape_tail):
        fail(path, f"{name!r} has shape {item.shape}: expected (n_samples, *{shape_tail})")
    return item


def _boresight_name(path, handle) -> str:
    names = sorted(n for n in handle["shared"] if n.startswith("boresight"))
    if "boresight_radec" in names:
        return "shared/boresight_radec"
    if len(names) != 1:
        fail(path, f"expected one shared boresight quaternion dataset, found {names}")
    return f"shared/{names[0]}"


class ToastLayout(NamedTuple):
    """What a TOAST observation file declares (:func:`toast_layout`)."""

    n_detectors: int  # kept: not flagged invalid
    n_samples: int
    sampling_rate_hz: float
    detectors: list[str]  # the kept detectors' names
    rows: list[int]  # their rows in detdata
    focalplane: object  # instrument/focalplane (astropy QTable)


def toast_layout(path) -> ToastLayout:
    """The detectors kept, samples, sampling rate and focal plane of a TOAST observation
    file, from its shapes, times, focal plane and detector flags (no TOD read).

    The rate is the focal plane's ``sample_rate``, checked against the times (to 1e-6);
    a ground observation (a site other than TOAST's ``SpaceSite``) is refused."""
    import h5py

    path = Path(path)
    with h5py.File(path, "r") as handle:
        version = int(handle.attrs["toast_format_version"])
        if version not in (1, 2):
            fail(path, f"toast_format_version {version}: this reader knows versions 1 and 2")
        if "observation_detectors" not in handle.attrs:
            fail(path, "TOAST file without the 'observation_detectors' attribute")
        site = (
            _decode(handle["instrument"].attrs.get("site_class", ""))
            if "instrument" in handle
            else ""
        )
        if site and not site.endswith("SpaceSite"):
            fail(
                path,
                f"a ground observation (site {site}): the nominal model is a satellite's "
                "(ecliptic scan, no atmosphere); expected a SpaceSite observation",
            )
        times = _dataset(path, handle, "shared/times")
        n = times.shape[0]
        if n < MIN_SAMPLES:
            fail(path, f"{n} samples: expected at least {MIN_SAMPLES}")
        ends = times[[0, n - 1]]
        names = json.loads(_decode(handle.attrs["observation_detectors"]))
        flags = json.loads(_decode(handle.attrs.get("observation_detector_flags", "{}")))
        signal = _dataset(path, handle, "detdata/signal")
        if isinstance(signal, h5py.Dataset) and signal.shape != (len(names), n):
            fail(
                path,
                f"detdata/signal has shape {signal.shape}: expected {(len(names), n)} "
                "(observation_detectors x shared/times)",
            )
    span_s = float(ends[1] - ends[0])
    if not (math.isfinite(span_s) and span_s > 0):
        fail(path, f"shared/times runs from {ends[0]!r} to {ends[1]!r}: expected increasing")
    rate_hz = (n - 1) / span_s
    focalplane = _focalplane_table(path)
    declared = focalplane.meta.get("sample_rate")
    if declared is not None:
        declared_hz = (
            float(declared.to_value("Hz")) if hasattr(declared, "to_value") else float(declared)
        )
        if abs(declared_hz / rate_hz - 1) > 1e-6:
            fail(
                path,
                f"the focal plane's sample_rate {declared_hz:g} Hz disagrees with shared/times "
                f"({rate_hz:.9g} Hz over {n} samples): expected evenly spaced samples at that rate",
            )
        rate_hz = declared_hz
    rows = [k for k, name in enumerate(names) if not int(flags.get(name, 0)) & DET_MASK_INVALID]
    if not rows:
        fail(path, f"every detector of {names} is flagged invalid (observation_detector_flags)")
    kept = [names[k] for k in rows]
    return ToastLayout(len(kept), n, rate_hz, kept, rows, focalplane)


def _focalplane_table(path):
    from astropy.table import QTable

    try:
        return QTable.read(path, path="instrument/focalplane")
    except (OSError, KeyError, ValueError) as error:
        fail(path, f"cannot read instrument/focalplane as a table ({error})")


def _focalplane(path, table, names: list[str]) -> list:
    """The focal plane's rows of the detectors ``names``, its needed columns checked."""
    rows = {_decode(row["name"]): row for row in table}
    missing = [name for name in names if name not in rows]
    if missing:
        fail(path, f"detectors {missing} are not in instrument/focalplane")
    for column in ("quat", "gamma"):
        if column not in table.colnames:
            fail(path, f"instrument/focalplane has no {column!r} column ({table.colnames})")
    return [rows[name] for name in names]


def _value(row, column: str, unit: str | None, default=None):
    """A focal-plane value in ``unit`` (a plain number if the column has no unit)."""
    if column not in row.colnames:
        return default
    value = row[column]
    if hasattr(value, "to_value"):
        return float(value.to_value(unit)) if unit else float(value.value)
    return float(value)


def _detector(row, channel: str) -> dict:
    """A detector's metadata in the recording's keys (see :class:`.recording.Recording`)."""
    leakage = _value(row, "pol_leakage", None, 0.0)
    detector = {
        "name": _decode(row["name"]),
        "pol_angle_rad": float(np.mod(2 * _value(row, "gamma", "rad") - np.pi / 2, np.pi)),
        "pol_efficiency": (1 - leakage) / (1 + leakage),
        "net_ukrts": _value(row, "psd_net", "uK s(1/2)"),
        "fknee_mhz": _value(row, "psd_fknee", "mHz"),
        "fmin_hz": _value(row, "psd_fmin", "Hz"),
        "alpha": _value(row, "psd_alpha", None),
        "bandcenter_ghz": _value(row, "bandcenter", "GHz"),
        "fwhm_arcmin": _value(row, "fwhm", "arcmin"),
    }
    detector = {key: value for key, value in detector.items() if value is not None}
    for key in GROUP_KEYS:  # the focal-plane groups (wafer, readout line, pixel)
        if key in row.colnames:
            value = row[key]
            detector[key] = (
                _decode(value) if isinstance(value, (bytes, str)) else np.asarray(value).item()
            )
    if channel:
        detector["channel"] = channel
    return detector


def _channel(row) -> str:
    """The instrument model's channel named by a ``channel`` or ``band`` column, else ''."""
    from .recording import known_channels

    for column in ("channel", "band"):
        if column in row.colnames and _decode(row[column]) in known_channels():
            return _decode(row[column])
    return ""


def _frame_rotations():
    """Rotations (scipy) from each candidate frame to litebird_sim's ecliptic frame."""
    import healpy as hp
    from scipy.spatial.transform import Rotation

    from ..simulation.data_model import ecliptic_to_galactic

    equatorial_to_ecliptic = Rotation.from_matrix(hp.Rotator(coord=["C", "E"]).mat)
    _, e2g = ecliptic_to_galactic()
    galactic_to_ecliptic = Rotation.from_quat(np.asarray(e2g.quats, dtype=float).ravel()).inv()
    return {
        "C": equatorial_to_ecliptic,
        "E": Rotation.identity(),
        "G": galactic_to_ecliptic,
    }


def _angle_deg(a, b) -> float:
    cosine = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def pointing_frame(path, time_unix: float, position_km, velocity_km_s):
    """The frame (C, E or G) of a TOAST satellite observation and its rotation to ecliptic,
    from the spacecraft's recorded position and velocity at ``time_unix``: the frame in
    which the Earth's (astropy) direction and velocity direction agree with them."""
    from astropy.coordinates import get_body_barycentric_posvel

    time = astropy.time.Time(time_unix, format="unix")
    earth_p, earth_v = get_body_barycentric_posvel("earth", time)
    rotations = _frame_rotations()
    misfit = {}
    for frame, to_ecliptic in rotations.items():
        # the Earth in this frame: ICRS (= C) -> ecliptic -> frame
        to_frame = to_ecliptic.inv() * rotations["C"]
        p = to_frame.apply(earth_p.xyz.to_value("km"))
        v = to_frame.apply(earth_v.xyz.to_value("km/s"))
        misfit[frame] = max(_angle_deg(p, position_km), _angle_deg(v, velocity_km_s))
    ranked = sorted(misfit, key=misfit.get)
    best, second = ranked[0], ranked[1]
    if misfit[best] > FRAME_TOLERANCE_DEG or misfit[second] < FRAME_SEPARATION_DEG:
        fail(
            path,
            "the pointing's frame cannot be told from the spacecraft's position and "
            f"velocity (angles from the Earth's in C, E, G: "
            f"{ {k: round(v, 2) for k, v in misfit.items()} } deg; expected one below "
            f"{FRAME_TOLERANCE_DEG} and the others above {FRAME_SEPARATION_DEG})",
        )
    return best, rotations[best]


def _orbit(start_time, span_s: float, times_s, velocity_ecl_km_s, position_ecl_km):
    """litebird_sim's position/velocity table (every ~ORBIT_STEP_S over the recording)."""
    import litebird_sim as lbs

    n_table = max(2, math.ceil(span_s / ORBIT_STEP_S) + 1)
    grid = np.linspace(0.0, span_s, n_table)
    position, velocity = (
        np.column_stack([np.interp(grid, times_s, v[:, i]) for i in range(3)])
        for v in (position_ecl_km, velocity_ecl_km_s)
    )
    orbit = lbs.SpacecraftOrbit(start_time)
    # as lbs.spacecraft_pos_and_vel: the Sun's velocity in the CMB frame added
    velocity += orbit.solar_velocity_ecl_xyz_km_s[np.newaxis, :]
    return lbs.SpacecraftPositionAndVelocity(
        orbit,
        start_time=start_time,
        time_span_s=span_s,
        positions_km=position,
        velocities_km_s=velocity,
    )


def _signal(path, handle, start: int, stop: int, rows: list[int]) -> np.ndarray:
    """detdata/signal for the kept detectors, samples start:stop, in K."""
    import astropy.units as u
    import h5py

    item = _dataset(path, handle, "detdata/signal")
    units = _decode(item.attrs.get("units", "K"))
    try:
        scale = u.Unit(units).to(u.K)
    except (ValueError, u.UnitConversionError):
        fail(path, f"detdata/signal in {units!r}: expected a temperature (K, mK, uK; K_CMB)")
    if isinstance(item, h5py.Dataset):
        return np.asarray(item[rows, start:stop], dtype=float) * scale
    try:
        import flacarray.hdf5
    except ImportError:
        fail(
            path,
            "detdata/signal is compressed (FLAC): reading it needs flacarray "
            "(pip install 'hwp_tes_systematics[toast]')",
        )
    values = np.asarray(flacarray.hdf5.read_array(item), dtype=float)
    return values[rows, start:stop] * scale


def read_toast_recording(path, memory_budget_bytes=None, samples=None) -> Recording:
    """Read a TOAST 3 observation file as a :class:`.recording.Recording` (module doc).

    ``samples``: (start, stop), only those samples (a segment, as :func:`.read_recording`).
    The diagnosis's memory is checked from the declared sizes before the data are read.
    """
    import h5py
    from scipy.spatial.transform import Rotation

    from ..simulation.data_model import quaternion_pointing

    path = Path(path)
    layout = toast_layout(path)
    n_det, n_file, rate_hz, rows = (
        layout.n_detectors,
        layout.n_samples,
        layout.sampling_rate_hz,
        layout.rows,
    )
    start, stop = (0, n_file) if samples is None else (int(samples[0]), int(samples[1]))
    if not 0 <= start < stop <= n_file or stop - start < MIN_SAMPLES:
        fail(path, f"samples {start}:{stop}: expected at least {MIN_SAMPLES} of {n_file}")
    check_memory(path, n_det, stop - start, rate_hz, memory_budget_bytes)
    rows_fp = _focalplane(path, layout.focalplane, layout.detectors)
    with h5py.File(path, "r") as handle:
        times = np.asarray(_dataset(path, handle, "shared/times")[start:stop], dtype=float)
        boresight = np.asarray(
            _dataset(path, handle, _boresight_name(path, handle), (4,))[start:stop], dtype=float
        )
        if "hwp_angle" not in handle["shared"]:
            fail(path, "no shared/hwp_angle: the diagnosis is of a recording with a rotating HWP")
        hwp = np.asarray(_dataset(path, handle, "shared/hwp_angle")[start:stop], dtype=float)
        position = np.asarray(_dataset(path, handle, "shared/position", (3,))[start:stop])
        velocity = np.asarray(_dataset(path, handle, "shared/velocity", (3,))[start:stop])
        tod = _signal(path, handle, start, stop, rows)
        flags = np.zeros(tod.shape, dtype=bool)
        if "flags" in handle["detdata"]:
            flags |= (
                np.asarray(handle["detdata/flags"][rows, start:stop]) & DET_MASK_NONSCIENCE
            ) != 0
        if "flags" in handle["shared"]:
            shared = np.asarray(handle["shared/flags"][start:stop]) & SHARED_MASK_NONSCIENCE
            flags |= shared[None, :] != 0
    frame, to_ecliptic = pointing_frame(path, times[0], position[0], velocity[0])
    pointings = np.empty((n_det, stop - start, 3))
    bore = Rotation.from_quat(boresight)
    for k, row in enumerate(rows_fp):
        detector = to_ecliptic * bore * Rotation.from_quat(np.asarray(row["quat"], dtype=float))
        quaternion_pointing(np.ascontiguousarray(detector.as_quat()), angles_out=pointings[k])
    channel = _channel(rows_fp[0])
    detectors = [_detector(row, channel) for row in rows_fp]
    mask_bad_samples(path, tod, pointings, hwp, flags, detectors)
    start_time = astropy.time.Time(times[0], format="unix", scale="utc")
    span_s = (stop - start - 1) / rate_hz
    orbit = _orbit(
        start_time,
        span_s,
        times - times[0],
        to_ecliptic.apply(velocity),
        to_ecliptic.apply(position),
    )
    return Recording(
        tod=tod,
        times_s=np.arange(stop - start) / rate_hz,
        sampling_rate_hz=rate_hz,
        hwp_angle_rad=hwp,
        pointings_ecl=pointings,
        detectors=detectors,
        start_time=start_time,
        flags=flags,
        channel=channel,
        source=f"{path} (TOAST, frame {frame})",
        orbit=orbit,
    )
