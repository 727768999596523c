"""Recordings: TOD of a detector pair with pointing and HWP angle, in litebird_sim's HDF5 format.

File format (what ``lbs.write_list_of_observations(..., write_full_pointings=True,
tod_dtype=None)`` writes, read back here with h5py):

* ``tod`` (n_det, n) K_CMB, float64 (litebird_sim writes float32 unless ``tod_dtype=None``;
  float32 would round the 0.3 K HWPSS at the 2e-8 K level), with attributes
  ``sampling_rate_hz``, ``detectors`` (JSON list of DetectorInfo fields: name,
  pol_angle_rad, pol_efficiency, net_ukrts, fknee_mhz, fmin_hz, alpha, bandcenter_ghz, ...),
  ``start_time`` and ``mjd_time``. With ``mjd_time`` true, ``start_time`` is the MJD string
  of the observation's astropy Time *in its own time scale* (litebird_sim calls
  ``to_value("mjd", "bytes")``): our simulations start in TDB, so the MJD is a TDB one,
  while litebird_sim's reader interprets it as UTC (69 s off, ~1e-9 K in the dipole). We
  therefore also write ``start_time_scale`` ("tdb") and read the MJD in that scale; a file
  without it is read as litebird_sim reads it (UTC).
* ``pointings`` (n_det, n, 3): ecliptic theta, phi, psi [rad] of each detector;
  ``hwp_angle`` (n,) [rad].
* optional flags, True/non-zero = bad sample: a ``flags`` dataset (n_det, n) or
  litebird_sim's run-length-encoded ``flags_NNNN`` datasets (``local_flags``).

Bad samples. NaN samples of the TOD, pointing or HWP angle are MASKED: their flag is set
and their value replaced by 0 so that no NaN reaches the arithmetic; the diagnosis uses
only unflagged samples. Inf is a corrupted value, not a gap: an Inf in an unflagged sample
is an error (an Inf in an already flagged sample is masked like a NaN). A file (or a
detector) without any valid sample is an error. Every error is a :class:`RecordingError`
(a ValueError) whose message names the file and the problem.

:func:`simulate_recording` makes a recording with :class:`~hwp_tes_systematics.simulation.tod.PairSimulator`
(sky + dipole + HWPSS + noise) and injects effects of the catalog through the same
forward models (:mod:`.effects`), or a TES nonlinearity through the electrothermal model
(``tes_electrothermal``): optical power P = P0 + d / C [W], current I = I(P) from
``tes.solve_operating_point`` and the linearly calibrated response
d_rec = C [I(P) - I(P0)] / S0, S0 = dI/dP at P0, C [K/W].

Injection order: effects on the sky signal (time constant, HWPSS harmonics, intensity
coupling, gain, HWP temperature, crosstalk, in the order given) -> + noise (white + 1/f,
litebird_sim, its own seed; ``noise_mismatch`` changes its NET/f_knee/alpha) -> detector
nonlinearity (polynomial or electrothermal) on the total -> + glitches.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import astropy.time
import numpy as np

from .. import seeding
from ..io import atomic_path
from ..simulation import data_model
from .effects import CATALOG, RESPONSE_STAGE, SIGNAL_EFFECTS, GlitchEvent, get_effect
from .model import Context, per_detector

DEFAULT_START_TDB = "2032-04-01T00:00:00"
REQUIRED_DETECTOR_KEYS = ("name", "pol_angle_rad")
MIN_SAMPLES = 64


class RecordingError(ValueError):
    """A recording file that cannot be used; the message names the file and the problem."""


@dataclass
class Recording:
    """TOD of one detector pair with its pointing; flagged samples hold 0 in ``tod``."""

    tod: np.ndarray  # (n_det, n) K_CMB
    times_s: np.ndarray  # (n,) s from the start
    sampling_rate_hz: float
    hwp_angle_rad: np.ndarray  # (n,)
    pointings_ecl: np.ndarray  # (n_det, n, 3) ecliptic theta, phi, psi [rad]
    detectors: list[dict]  # name, pol_angle_rad, net_ukrts, fknee_mhz, alpha, fmin_hz, ...
    start_time: astropy.time.Time
    flags: np.ndarray  # (n_det, n) bool, True = bad sample
    channel: str = ""
    source: str = "<memory>"
    observation: object = field(default=None, repr=False, compare=False)
    injected: list = field(default_factory=list, repr=False, compare=False)

    @property
    def n_detectors(self) -> int:
        return self.tod.shape[0]

    @property
    def n_samples(self) -> int:
        return self.tod.shape[1]

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.sampling_rate_hz

    @property
    def detector_names(self) -> list[str]:
        return [str(d["name"]) for d in self.detectors]

    @property
    def pol_angles_rad(self) -> np.ndarray:
        return np.array([float(d["pol_angle_rad"]) for d in self.detectors])

    @property
    def pol_efficiency(self) -> np.ndarray:
        return np.array([float(d.get("pol_efficiency", 1.0)) for d in self.detectors])

    def nominal_noise(self) -> list[dict]:
        """Configured noise per detector: net_ukrts, fknee_mhz, alpha, fmin_hz."""
        return [
            {
                "net_ukrts": float(d.get("net_ukrts", math.nan)),
                "fknee_mhz": float(d.get("fknee_mhz", 0.0)),
                "alpha": float(d.get("alpha", 1.0)),
                "fmin_hz": float(d.get("fmin_hz", 1e-5)),
            }
            for d in self.detectors
        ]


# --------------------------------------------------------------------------- reading


def _fail(path, problem: str):
    raise RecordingError(f"{path}: {problem}")


def _read_start_time(path, dataset) -> astropy.time.Time:
    attrs = dataset.attrs
    if "start_time" not in attrs:
        _fail(path, "dataset 'tod' has no 'start_time' attribute")
    value = attrs["start_time"]
    if isinstance(value, bytes):
        value = value.decode()
    if not bool(attrs.get("mjd_time", True)):
        _fail(
            path,
            f"start_time = {value!r} s is not an absolute time (mjd_time = False): the "
            "orbital dipole needs the date of the observation",
        )
    scale = attrs.get("start_time_scale", "utc")
    if isinstance(scale, bytes):
        scale = scale.decode()
    try:
        return astropy.time.Time(str(value), format="mjd", scale=str(scale))
    except ValueError as error:
        _fail(path, f"start_time = {value!r} (scale {scale!r}) is not an MJD ({error})")


def _read_detectors(path, dataset, n_det: int) -> list[dict]:
    text = dataset.attrs.get("detectors")
    if text is None:
        _fail(path, "dataset 'tod' has no 'detectors' attribute (JSON list of detectors)")
    try:
        detectors = json.loads(text)
    except (TypeError, json.JSONDecodeError) as error:
        _fail(path, f"attribute 'detectors' is not valid JSON ({error})")
    if not isinstance(detectors, list) or len(detectors) != n_det:
        _fail(path, f"attribute 'detectors' lists {len(detectors)} detectors, 'tod' has {n_det}")
    for index, detector in enumerate(detectors):
        missing = [key for key in REQUIRED_DETECTOR_KEYS if key not in detector]
        if missing:
            _fail(path, f"detector {index} of attribute 'detectors' lacks {missing}")
    return detectors


def _read_flags(path, handle, n_det: int, n: int) -> np.ndarray:
    flags = np.zeros((n_det, n), dtype=bool)
    if "flags" in handle:
        data = handle["flags"][()]
        if data.shape != (n_det, n):
            _fail(path, f"dataset 'flags' has shape {data.shape}, expected {(n_det, n)}")
        flags |= data.astype(bool)
    names = [name for name in handle if name.startswith("flags_") and name[6:].isdigit()]
    if names:
        from litebird_sim.compress import rle_decompress

        for name in names:
            index = int(name[6:])
            if index >= n_det:
                _fail(path, f"dataset {name!r} refers to detector {index} of {n_det}")
            values = np.asarray(rle_decompress(handle[name][()]))
            if values.size != n:
                _fail(path, f"dataset {name!r} decodes to {values.size} samples, 'tod' has {n}")
            flags[index] |= values.astype(bool)
    return flags


def read_recording(path) -> Recording:
    """Read a recording written by :func:`write_recording` (litebird_sim's HDF5 format).

    A file that h5py cannot open or read (truncated by an interrupted copy or write, or
    corrupt) is a :class:`RecordingError` naming the file, what h5py said and what to do.
    """
    path = Path(path)
    try:
        return _read_recording(path)
    except OSError as error:  # h5py: "Unable to synchronously open file (truncated file...)"
        size = path.stat().st_size if path.exists() else 0
        _fail(
            path,
            f"cannot be read as HDF5 ({error}; {size} bytes on disk): the file is truncated "
            "or corrupt, e.g. by an interrupted copy or write; copy or write it again "
            "(compare its size or checksum with the original)",
        )


def _read_recording(path: Path) -> Recording:
    import h5py

    if not path.exists():
        _fail(path, "no such file")
    if not path.is_file() or not h5py.is_hdf5(path):
        _fail(path, "not an HDF5 file (expected a litebird_sim observation file)")
    with h5py.File(path, "r") as handle:
        for name in ("tod", "pointings", "hwp_angle"):
            if name not in handle or not isinstance(handle[name], h5py.Dataset):
                hint = (
                    " (write the observation with write_full_pointings=True)"
                    if name != "tod"
                    else ""
                )
                _fail(path, f"missing dataset {name!r}{hint}")
        dataset = handle["tod"]
        if dataset.ndim != 2:
            _fail(path, f"dataset 'tod' has shape {dataset.shape}, expected (n_det, n_samples)")
        n_det, n = dataset.shape
        if n < MIN_SAMPLES or n_det < 1:
            _fail(path, f"dataset 'tod' has shape {dataset.shape}: too few samples/detectors")
        pointings = handle["pointings"]
        if pointings.shape != (n_det, n, 3):
            _fail(
                path,
                f"length mismatch: 'pointings' has shape {pointings.shape}, 'tod' {(n_det, n)} "
                f"(expected {(n_det, n, 3)})",
            )
        hwp = handle["hwp_angle"]
        if hwp.shape != (n,):
            _fail(
                path, f"length mismatch: 'hwp_angle' has shape {hwp.shape}, 'tod' has {n} samples"
            )
        try:
            sampling_rate_hz = float(dataset.attrs["sampling_rate_hz"])
        except KeyError:
            _fail(path, "dataset 'tod' has no 'sampling_rate_hz' attribute")
        if not (math.isfinite(sampling_rate_hz) and sampling_rate_hz > 0):
            _fail(path, f"sampling_rate_hz = {sampling_rate_hz!r}: expected a rate > 0 Hz")
        detectors = _read_detectors(path, dataset, n_det)
        start_time = _read_start_time(path, dataset)
        try:
            tod = np.asarray(dataset[()], dtype=float)
            pointings_ecl = np.asarray(pointings[()], dtype=float)
            hwp_angle = np.asarray(hwp[()], dtype=float)
        except (TypeError, ValueError) as error:
            _fail(path, f"non-numeric data ({error})")
        flags = _read_flags(path, handle, n_det, n)

    # NaN = gap (masked); Inf = corruption (error unless already flagged).
    for name, values, per_sample in (
        ("tod", tod, tod),
        ("pointings", pointings_ecl, None),
        ("hwp_angle", hwp_angle, None),
    ):
        infinite = np.isinf(values)
        if per_sample is None and name == "pointings":
            infinite_samples = infinite.any(axis=-1)
        elif name == "hwp_angle":
            infinite_samples = np.broadcast_to(infinite, (n_det, n))
        else:
            infinite_samples = infinite
        unflagged = infinite_samples & ~flags
        if unflagged.any():
            k, i = np.argwhere(unflagged)[0]
            _fail(
                path,
                f"{int(unflagged.sum())} Inf value(s) in unflagged samples of {name!r} "
                f"(first: detector {k}, sample {i}); flag them or replace them by NaN",
            )
    nan_tod = ~np.isfinite(tod)
    nan_pointing = ~np.isfinite(pointings_ecl).all(axis=-1)
    nan_hwp = ~np.isfinite(hwp_angle)
    flags |= nan_tod | nan_pointing | nan_hwp[None, :]
    if flags.all():
        _fail(path, "no valid sample: every sample is NaN or flagged")
    for k in range(n_det):
        if flags[k].all():
            _fail(path, f"detector {detectors[k]['name']!r} has no valid sample (all NaN/flagged)")
    tod[flags] = 0.0
    pointings_ecl[~np.isfinite(pointings_ecl)] = 0.0
    hwp_angle[nan_hwp] = 0.0
    if nan_hwp.any():  # the HWP turns uniformly: bridge the gap so chi stays usable
        good = ~nan_hwp
        unwrapped = np.unwrap(hwp_angle[good])
        filled = np.interp(np.arange(n), np.flatnonzero(good), unwrapped)
        # back on the file's branch: (-pi, pi] or [0, 2 pi)
        offset = np.pi if hwp_angle[good].min() < 0 else 0.0
        hwp_angle[nan_hwp] = np.mod(filled[nan_hwp] + offset, 2 * np.pi) - offset
    channel = str(detectors[0].get("channel", ""))
    return Recording(
        tod=tod,
        times_s=np.arange(n) / sampling_rate_hz,
        sampling_rate_hz=sampling_rate_hz,
        hwp_angle_rad=hwp_angle,
        pointings_ecl=pointings_ecl,
        detectors=detectors,
        start_time=start_time,
        flags=flags,
        channel=channel,
        source=str(path),
    )


def known_channels() -> set[str]:
    """Channel names of the instrument model (litebird_sim's PTEP IMO)."""
    from ..instrument.channels import channel_names_by_telescope

    return {name for names in channel_names_by_telescope().values() for name in names}


def nominal_a2(recording: Recording, a2_k: float | None, lookup) -> float:
    """The nominal A_2 [K]: ``a2_k`` if given (``--a2``), else ``lookup(channel)``.

    A recording whose channel the instrument model does not know (a lab detector: no or
    an unknown ``channel`` in its detector metadata) is diagnosed from its own metadata
    (NET, sampling rate, polarisation angles) and needs A_2 from the caller; without it
    the error says what to supply.
    """
    if a2_k is not None:
        if not (math.isfinite(a2_k) and a2_k >= 0):
            raise RecordingError(f"--a2 = {a2_k!r}: expected an amplitude >= 0 in K_CMB")
        return float(a2_k)
    channel = recording.channel
    if not channel or channel not in known_channels():
        _fail(
            recording.source,
            f"channel {channel!r} of detectors {recording.detector_names} is not in the "
            "instrument model, so its nominal HWPSS amplitude is unknown: give it with "
            "--a2 A2_K (K_CMB; e.g. --a2 0.264)",
        )
    return float(lookup(channel))


# --------------------------------------------------------------------------- writing


def _json_safe(detector: dict) -> dict:
    safe = {}
    for key, value in detector.items():
        if isinstance(value, (str, bool, int, float)) or value is None:
            safe[key] = value
        elif isinstance(value, np.generic):
            safe[key] = value.item()
        elif isinstance(value, (list, tuple, np.ndarray)):
            try:
                safe[key] = np.asarray(value, dtype=float).tolist()
            except (TypeError, ValueError):
                continue
    return safe


def _observation_for(recording: Recording):
    """The litebird_sim Observation holding the recording (the simulator's, if it has one)."""
    import litebird_sim as lbs

    observation = recording.observation
    if (
        observation is not None
        and getattr(observation, "pointing_provider", None) is not None
        and observation.tod.shape == recording.tod.shape
    ):
        observation.tod[:] = recording.tod
        return observation, True
    detectors = []
    for detector in recording.detectors:
        detector = dict(detector)
        detector.setdefault("quat", lbs.RotQuaternion())
        detectors.append(detector)
    observation = lbs.Observation(
        detectors=detectors,
        n_samples_global=recording.n_samples,
        start_time_global=recording.start_time,
        sampling_rate_hz=recording.sampling_rate_hz,
        tods=[lbs.TodDescription("tod", lbs.Units.K_CMB, np.float64, "recorded TOD")],
    )
    observation.tod[:] = recording.tod
    return observation, False


def write_recording(path, recording: Recording) -> Path:
    """Write ``recording`` as one litebird_sim HDF5 observation file at ``path`` (atomically).

    ``lbs.write_list_of_observations([obs], ..., write_full_pointings=True, tod_dtype=None)``
    writes the TOD (float64), detectors, start time, pointings and HWP angle when the
    observation carries its pointing provider (recordings from :func:`simulate_recording`);
    otherwise the same ``pointings``/``hwp_angle`` datasets are added with h5py. Flags go
    to a ``flags`` dataset; ``start_time_scale`` records the time scale of the MJD.
    """
    import h5py
    import litebird_sim as lbs

    path = Path(path)
    observation, _ = _observation_for(recording)
    flags = np.asarray(recording.flags, dtype=bool)
    with atomic_path(path) as temporary:
        lbs.write_list_of_observations(
            [observation],
            temporary.parent,
            tod_dtype=None,
            file_name_mask=temporary.name,
            collective_mpi_call=False,
            write_full_pointings=True,
        )
        with h5py.File(temporary, "a") as handle:
            if "pointings" not in handle:
                handle.create_dataset("pointings", data=recording.pointings_ecl, dtype=np.float64)
            if "hwp_angle" not in handle:
                handle.create_dataset("hwp_angle", data=recording.hwp_angle_rad, dtype=np.float64)
            if flags.any():
                handle.create_dataset("flags", data=flags.astype(np.uint8), compression="gzip")
            handle["tod"].attrs["start_time_scale"] = recording.start_time.scale
    return path


# --------------------------------------------------------------------------- simulating


@functools.lru_cache(maxsize=4)
def _simulated_base(channel_name: str, hours: float, start_time_tdb: str, nside: int):
    """PairSimulator, pointing and dipole of a recording (noise-free pieces), cached."""
    from ..instrument.channels import load_channel
    from ..simulation.tod import MissionPlan, PairSimulator

    channel = load_channel(channel_name)
    duration_s = hours * 3600.0
    plan = MissionPlan(start_time_tdb, duration_s, duration_s, channel.sampling_rate_hz)
    simulator = PairSimulator(channel, plan, nside)
    pointing = simulator.pointing(0, plan.n_samples)
    dipole = simulator.dipole(pointing)
    return simulator, pointing, dipole


def _detector_dicts(simulator) -> list[dict]:
    return [_json_safe(asdict(detector)) for detector in simulator.detectors]


def _electrothermal(tod: np.ndarray, params: dict) -> np.ndarray:
    """d_rec = C [I(P0 + d / C) - I(P0)] / S0 through the electrothermal TES model."""
    from scipy.interpolate import CubicSpline

    from ..instrument import tes

    p0_w = float(params["p0_w"])
    kelvin_per_watt = float(params["kelvin_per_watt"])
    tes_params = params.get("tes_parameters")
    if tes_params is None:
        tes_params = tes.tes_parameters_for_channel(
            p0_w,
            psat_factor=float(params.get("psat_factor", 2.5)),
            resistance_fraction=float(params.get("resistance_fraction", 0.7)),
            **dict(params.get("overrides", {})),
        )
    power_w = p0_w + tod / kelvin_per_watt
    lo, hi = float(power_w.min()), float(power_w.max())
    margin = 0.01 * (hi - lo) + 1e-18
    grid = np.linspace(max(lo - margin, 0.0), hi + margin, 2001)
    spline = CubicSpline(grid, tes.solve_operating_point(tes_params, grid).current_a)
    current0 = float(tes.solve_operating_point(tes_params, p0_w).current_a)
    responsivity0 = float(tes.responsivity_a_per_w(tes_params, p0_w))
    return kelvin_per_watt * (spline(power_w) - current0) / responsivity0


def _noise(simulator, pointing, master_seed, noise_seed, params: dict | None) -> np.ndarray:
    """White + 1/f noise of litebird_sim (chunk 0 streams of PairSimulator.noise)."""
    if not params:
        return simulator.noise(pointing, master_seed, noise_seed, 0)
    from litebird_sim.noise import add_one_over_f_noise

    channel = simulator.channel
    n = pointing.hwp_angle_rad.size
    n_det = simulator.n_detectors
    out = np.zeros((n_det, n))
    detectors = simulator.detectors

    def value(key):
        default = [getattr(d, key) for d in detectors]
        return per_detector(params.get(key, default), n_det, key)

    net, fknee, alpha, fmin = (value(key) for key in ("net_ukrts", "fknee_mhz", "alpha", "fmin_hz"))
    for k, name in enumerate(simulator.detector_names):
        generator = seeding.rng(master_seed, "noise", channel.name, noise_seed, 0, name)
        sigma = net[k] * np.sqrt(channel.sampling_rate_hz) / 1e6
        add_one_over_f_noise(
            out[k], fknee[k], fmin[k], alpha[k], sigma, channel.sampling_rate_hz, generator
        )
    return out


RESPONSE_EFFECTS = RESPONSE_STAGE | {"tes_electrothermal"}


def _hwpss_sine_modulation(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """A_2 [1 + m sin(2 pi t / P + phi)] cos(2 (chi - theta) - phi_2): a periodic 2f modulation.

    Modulates the recording's actual HWPSS: ``a2_k`` and ``hwpss_phase_rad`` (phi_2), when
    given, are its true amplitude and phase (default: the nominal ones).
    """
    relative = per_detector(params["relative"], ctx.n_detectors, "relative")
    a2 = per_detector(params.get("a2_k", ctx.a2_k), ctx.n_detectors, "a2_k")
    phase2 = per_detector(params.get("hwpss_phase_rad", 0.0), ctx.n_detectors, "hwpss_phase_rad")
    wave = np.sin(2 * np.pi * ctx.times_s / float(params["period_s"]) + params.get("phase_rad", 0))
    carrier = np.cos(2 * ctx.detector_angle - phase2[:, None])
    return tod + (relative * a2)[:, None] * wave[None, :] * carrier


def _pickup_line(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """A cos(2 pi f t + phi): an electrical pickup line at a frequency of no HWP/scan combination."""
    amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
    phase = 2 * np.pi * float(params["freq_hz"]) * ctx.times_s + params.get("phase_rad", 0.0)
    return tod + amplitude[:, None] * np.cos(phase)[None, :]


def _hwpss_spin_modulation(ctx: Context, params: dict, tod: np.ndarray) -> np.ndarray:
    """c_n [1 + m cos(2 pi f_spin t)] cos n(chi - theta): an HWP harmonic modulated by the spin.

    (An HWP wobble whose emission depends on the spin phase.) Lines at n f_HWP and
    n f_HWP +- f_spin; not a catalog effect: only its constant part is hwpss_harmonics.
    """
    n = int(params.get("harmonic", 3))
    amplitude = per_detector(params["amplitude_k"], ctx.n_detectors, "amplitude_k")
    depth = float(params.get("depth", 1.0))
    envelope = 1.0 + depth * np.cos(2 * np.pi * ctx.f_spin_hz * ctx.times_s)
    return tod + amplitude[:, None] * envelope[None, :] * np.cos(n * ctx.detector_angle)


# Effects OUTSIDE the catalog (no forward model in the diagnosis), for tests and benchmarks:
# signal effects, applied with the catalog's signal effects before the noise.
OUT_OF_CATALOG = {
    "hwpss_sine_modulation": _hwpss_sine_modulation,
    "pickup_line": _pickup_line,
    "hwpss_spin_modulation": _hwpss_spin_modulation,
}


def simulate_recording(
    channel_name: str,
    hours: float,
    master_seed: int,
    noise_seed: int,
    sky_iqu: np.ndarray,
    a2_k,
    effects=(),
    start_time_tdb: str = DEFAULT_START_TDB,
    pol_angle_offsets_rad=0.0,
) -> Recording:
    """A recording of ``channel_name``'s pair: sky + dipole + HWPSS + noise + injected effects.

    ``effects`` is a list of (name, params): catalog effects with their parameters (a
    scalar or one value per detector each; glitches as ``{"events": [(detector, time_s,
    amplitude_k, tau_s), ...]}``; noise_mismatch as ``{"net_ukrts", "fknee_mhz",
    "alpha"}``), or ``("tes_electrothermal", {"p0_w", "kelvin_per_watt", ...})``. The
    noise comes from its own stream ``(master_seed, "noise", channel, noise_seed, 0,
    detector)``. The truth is kept in ``recording.injected`` (never written to a file).
    ``pol_angle_offsets_rad``: the true polarisation angles are theta + delta while the
    recording's metadata keeps the nominal theta (a polarisation-angle error): the sky
    polarisation is rho [Q cos 2(a - delta) + U sin 2(a - delta)] and the HWPSS
    A_2 cos 2(chi - theta - delta).
    """
    from .model import check_sky_map

    sky = check_sky_map(sky_iqu)
    nside = round(np.sqrt(sky.shape[1] / 12))
    simulator, pointing, dipole = _simulated_base(channel_name, float(hours), start_time_tdb, nside)
    n_det = simulator.n_detectors
    a2 = per_detector(a2_k, n_det, "a2_k")
    unpolarized = np.stack([sky[0], np.zeros_like(sky[0]), np.zeros_like(sky[0])])
    sky_intensity = simulator.scan_sky(pointing, unpolarized)
    sky_polarization = simulator.scan_sky(pointing, sky) - sky_intensity
    delta = per_detector(pol_angle_offsets_rad, n_det, "pol_angle_offsets_rad")
    if np.any(delta != 0):
        quadrature = data_model.scan_quadrature(
            pointing.pixels,
            pointing.cos_2alpha,
            pointing.sin_2alpha,
            simulator.pol_efficiency,
            sky,
        )
        sky_polarization = (
            np.cos(2 * delta)[:, None] * sky_polarization + np.sin(2 * delta)[:, None] * quadrature
        )
    pol_angles = simulator.pol_angles_rad + delta
    n = pointing.hwp_angle_rad.size
    ctx = Context(
        times_s=np.arange(n) / simulator.plan.sampling_rate_hz,
        sampling_rate_hz=simulator.plan.sampling_rate_hz,
        hwp_angle_rad=pointing.hwp_angle_rad,
        pol_angle_rad=pol_angles,
        pol_efficiency=simulator.pol_efficiency,
        sky_intensity=sky_intensity,
        sky_polarization=sky_polarization,
        dipole=dipole,
        a2_k=a2,
        valid=np.ones((n_det, n), dtype=bool),
        detector_names=simulator.detector_names,
    )
    # The HWPSS of the data model (litebird_sim's add_2f), as the study's simulation.
    hwpss = data_model.hwpss(pointing.hwp_angle_rad, pol_angles, a2)
    signal = sky_intensity + sky_polarization + dipole + hwpss

    effects = [(str(name), dict(params)) for name, params in effects]
    for name, _ in effects:
        if name not in CATALOG and name not in RESPONSE_EFFECTS and name not in OUT_OF_CATALOG:
            raise KeyError(
                f"unknown effect {name!r}; expected one of {sorted(CATALOG)}, "
                f"{sorted(RESPONSE_EFFECTS)} or {sorted(OUT_OF_CATALOG)}"
            )
    for name, params in effects:
        if name in SIGNAL_EFFECTS:
            signal = get_effect(name).apply(ctx, params, signal)
        elif name in OUT_OF_CATALOG:
            signal = OUT_OF_CATALOG[name](ctx, params, signal)
    noise_params = next((p for name, p in effects if name == "noise_mismatch"), None)
    tod = signal + _noise(simulator, pointing, master_seed, noise_seed, noise_params)
    for name, params in effects:
        if name in RESPONSE_STAGE:
            tod = get_effect(name).apply(ctx, params, tod)
        elif name == "tes_electrothermal":
            tod = _electrothermal(tod, params)
    for name, params in effects:
        if name == "glitches":
            events = [
                e if isinstance(e, GlitchEvent) else GlitchEvent(*e) for e in params["events"]
            ]
            tod = get_effect(name).apply(ctx, {"events": events}, tod)

    return Recording(
        tod=tod,
        times_s=ctx.times_s.copy(),
        sampling_rate_hz=float(simulator.plan.sampling_rate_hz),
        hwp_angle_rad=np.array(pointing.hwp_angle_rad, dtype=float),
        pointings_ecl=np.array(pointing.ecliptic_rad(), dtype=float),
        detectors=_detector_dicts(simulator),
        start_time=simulator.plan.start_time,
        flags=np.zeros((n_det, n), dtype=bool),
        channel=channel_name,
        source=f"<simulated {channel_name}, {hours:g} h, noise seed {noise_seed}>",
        observation=pointing.observation,
        injected=effects,
    )
