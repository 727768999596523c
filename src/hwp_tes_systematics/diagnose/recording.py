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

Declared sizes are checked before anything is read: every dataset's shape, dtype (real
numbers; flags boolean or integer) and stored data (a dataset whose chunks or bytes
were never all written: a hostile or hand-built file declaring 1e10 samples in a few
MB) and the run lengths of
RLE flags, so that no array of a declared size is allocated before it is known to be
plausible and to fit in memory.

Recordings with injected effects are simulated by :mod:`.simulate`.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import astropy.time
import erfa
import numpy as np

from ..io import atomic_path
from .recording_checks import (
    MIN_SAMPLES,
    RecordingError,
    check_file,
    check_memory,
    declared_layout,
    fail,
    is_toast_file,
    recording_size,
    rle_flag_names,
)

DEFAULT_START_TDB = "2032-04-01T00:00:00"
# the detector metadata that group detectors on the focal plane (litebird_sim's DetectorInfo
# fields; a TOAST focal plane's columns of these names) -> what a group is called: what an
# effect shared per group (:attr:`.effects.base.Effect.group_by`) shares, in the order a
# key that splits the detectors as an earlier one does is dropped
GROUP_KEYS = {"wafer": "wafer", "squid": "readout line (SQUID)", "pixel": "pixel"}
REQUIRED_DETECTOR_KEYS = ("name", "pol_angle_rad")
FINITE_DETECTOR_KEYS = (
    "pol_angle_rad",
    "pol_efficiency",
    "net_ukrts",
    "fknee_mhz",
    "alpha",
    "fmin_hz",
)


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
    # the spacecraft's position and velocity the recording carries (a TOAST observation's),
    # for its dipole; None: litebird_sim's orbit from the start time (:func:`.model.dipole_tod`)
    orbit: object = field(default=None, repr=False, compare=False)

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

    @property
    def groups(self) -> dict[str, tuple[str, ...]]:
        """{key of GROUP_KEYS: each detector's group label}, for the keys every detector
        carries that split the detectors into 2 or more groups, one of them of 2 or more
        detectors (else a group is all detectors, or each its own); a key that splits
        them as an earlier one does is left out."""
        return detector_groups(self.detectors)

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


def detector_groups(detectors: list[dict]) -> dict[str, tuple[str, ...]]:
    """:attr:`Recording.groups` of the detectors' metadata ``detectors``."""
    out: dict[str, tuple[str, ...]] = {}
    partitions = set()
    for key in GROUP_KEYS:
        values = [detector.get(key) for detector in detectors]
        if any(value is None or value == "" for value in values):
            continue
        labels = tuple(str(value) for value in values)
        n_groups = len(set(labels))
        if not 2 <= n_groups < len(labels):
            continue
        first_seen = {label: i for i, label in reversed(list(enumerate(labels)))}
        partition = tuple(first_seen[label] for label in labels)
        if partition not in partitions:
            partitions.add(partition)
            out[key] = labels
    return out


def _read_start_time(path, dataset) -> astropy.time.Time:
    attrs = dataset.attrs
    if "start_time" not in attrs:
        fail(path, "dataset 'tod' has no 'start_time' attribute")
    value = attrs["start_time"]
    if isinstance(value, bytes):
        value = value.decode()
    if not bool(attrs.get("mjd_time", True)):
        fail(
            path,
            f"start_time = {value!r} s is not an absolute time (mjd_time = False): the "
            "orbital dipole needs the date of the observation",
        )
    scale = attrs.get("start_time_scale", "utc")
    if isinstance(scale, bytes):
        scale = scale.decode()
    try:
        start = astropy.time.Time(str(value), format="mjd", scale=str(scale))
        with warnings.catch_warnings():  # "dubious year": leap seconds after the table's end
            warnings.simplefilter("ignore", erfa.ErfaWarning)
            start.utc.isot  # noqa: B018 (ERFA refuses a date it cannot represent)
    except (ValueError, TypeError, astropy.time.ScaleValueError) as error:
        fail(
            path,
            f"attribute 'start_time' of dataset 'tod' = {value!r} (scale {scale!r}) is not "
            f"an MJD date ({type(error).__name__}: {error}); expected e.g. '63323.0' with "
            "start_time_scale 'tdb' or 'utc'",
        )
    return start


def _read_detectors(path, dataset, n_det: int) -> list[dict]:
    text = dataset.attrs.get("detectors")
    if text is None:
        fail(path, "dataset 'tod' has no 'detectors' attribute (JSON list of detectors)")
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    try:
        detectors = json.loads(text)
    except (TypeError, json.JSONDecodeError) as error:
        fail(path, f"attribute 'detectors' is not valid JSON ({error})")
    if not isinstance(detectors, list):
        fail(
            path,
            f"attribute 'detectors' of dataset 'tod' is a JSON {type(detectors).__name__}: "
            f"expected a list of {n_det} detector objects",
        )
    if len(detectors) != n_det:
        fail(path, f"attribute 'detectors' lists {len(detectors)} detectors, 'tod' has {n_det}")
    for index, detector in enumerate(detectors):
        if not isinstance(detector, dict):
            fail(
                path,
                f"detector {index} of attribute 'detectors' is {detector!r}: expected an "
                f"object with at least {list(REQUIRED_DETECTOR_KEYS)}",
            )
        missing = [key for key in REQUIRED_DETECTOR_KEYS if key not in detector]
        if missing:
            fail(path, f"detector {index} of attribute 'detectors' lacks {missing}")
        if not isinstance(detector["name"], str) or not detector["name"]:
            fail(
                path,
                f"detector {index} of attribute 'detectors' has name {detector['name']!r}: "
                "expected a non-empty string",
            )
        for key in FINITE_DETECTOR_KEYS:
            if key != "pol_angle_rad" and detector.get(key, 0.0) is None:
                del detector[key]  # null: not given (a NET then comes from the residual)
            if key not in detector:
                continue
            value = detector[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                finite = False
            else:
                finite = math.isfinite(value)
            if not finite:
                fail(
                    path,
                    f"detector {detector['name']!r} (attribute 'detectors') has {key} = "
                    f"{value!r}: expected a finite number",
                )
    return detectors


def _rle_segment(dataset, start: int, stop: int) -> np.ndarray:
    """Samples start:stop of one detector's RLE flags (checked by :func:`_check_flags`),
    decoded without decoding the rest: (stop - start,) bool."""
    runs = np.asarray(dataset[0], dtype=np.int64)
    values = np.asarray(dataset[1]) != 0
    ends = np.cumsum(runs)
    first = int(np.searchsorted(ends, start, side="right"))
    last = int(np.searchsorted(ends, stop, side="left"))
    lengths = runs[first : last + 1].copy()
    starts = ends[first : last + 1] - lengths
    lengths -= np.clip(start - starts, 0, None)
    lengths -= np.clip(ends[first : last + 1] - stop, 0, None)
    return np.repeat(values[first : last + 1], lengths)


def _read_flags(path, handle, n_det: int, start: int, stop: int) -> np.ndarray:
    """Flags of samples start:stop, (n_det, stop - start) bool; shapes already checked."""
    flags = np.zeros((n_det, stop - start), dtype=bool)
    if "flags" in handle:
        flags |= np.asarray(handle["flags"][:, start:stop]) != 0
    for name in rle_flag_names(handle):
        flags[int(name[6:])] |= _rle_segment(handle[name], start, stop)
    return flags


def read_recording(path, memory_budget_bytes=None, samples=None) -> Recording:
    """Read a recording written by :func:`write_recording` (litebird_sim's HDF5 format), or a
    TOAST 3 observation file (:mod:`.toast_recording`); a list of files: the detectors of
    one observation, written apart (:func:`merge_recordings`).

    ``samples``: (start, stop), read only those samples (a segment: its ``start_time`` is
    the file's plus start / sampling rate, its ``times_s`` start at 0), so that a
    recording longer than memory allows is diagnosed piece by piece (:mod:`.segments`).
    A file that h5py cannot open or read (truncated by an interrupted copy or write, or
    corrupt) is a :class:`RecordingError` naming the file, what h5py said and what to do;
    so is a file (or segment) whose declared size would need more memory to diagnose than
    ``memory_budget_bytes`` (default: the available memory; :func:`check_memory`),
    refused before any of its data is read.
    """
    if isinstance(path, (list, tuple)):
        paths = [Path(p) for p in path]
        if len(paths) > 1:
            n_det, n, rate = recording_size(paths)  # every file's layout, and the sum
            check_memory(", ".join(map(str, paths)), n_det, n, rate, memory_budget_bytes)
            return merge_recordings([read_recording(p, math.inf, samples) for p in paths])
        (path,) = paths
    path = Path(path)
    try:
        check_file(path)
        if is_toast_file(path):
            from .toast_recording import read_toast_recording

            return read_toast_recording(path, memory_budget_bytes, samples)
        return _read_recording(path, memory_budget_bytes, samples)
    except OSError as error:  # h5py: "Unable to synchronously open file (truncated file...)"
        size = path.stat().st_size if path.exists() else 0
        fail(
            path,
            f"cannot be read as HDF5 ({error}; {size} bytes on disk): the file is truncated "
            "or corrupt, e.g. by an interrupted copy or write; copy or write it again "
            "(compare its size or checksum with the original)",
        )


def merge_recordings(parts: list[Recording]) -> Recording:
    """One recording of the detectors of ``parts``, files of one observation: the same
    samples, start (to half a sample), sampling rate and HWP angle (to 1e-6 rad), distinct
    detector names; else a :class:`RecordingError` naming the files."""
    first = parts[0]
    names = ", ".join(part.source for part in parts)
    for part in parts[1:]:
        where = f"{first.source} and {part.source}"
        if part.n_samples != first.n_samples or part.sampling_rate_hz != first.sampling_rate_hz:
            fail(
                where,
                f"{first.n_samples} and {part.n_samples} samples at {first.sampling_rate_hz:g} "
                f"and {part.sampling_rate_hz:g} Hz: not the detectors of one observation",
            )
        offset_s = float((part.start_time - first.start_time).to_value("s"))
        if abs(offset_s) > 0.5 / first.sampling_rate_hz:
            fail(where, f"start {offset_s:.6g} s apart: not the same observation")
        hwp = np.angle(np.exp(1j * (part.hwp_angle_rad - first.hwp_angle_rad)))
        if np.max(np.abs(hwp)) > 1e-6:
            fail(where, f"HWP angles differ by up to {np.max(np.abs(hwp)):.3g} rad")
    detectors = [d for part in parts for d in part.detectors]
    seen = [d["name"] for d in detectors]
    twice = sorted({name for name in seen if seen.count(name) > 1})
    if twice:
        fail(names, f"detector(s) {twice} in more than one file")
    channels = {part.channel for part in parts}
    return Recording(
        tod=np.concatenate([part.tod for part in parts]),
        times_s=first.times_s,
        sampling_rate_hz=first.sampling_rate_hz,
        hwp_angle_rad=first.hwp_angle_rad,
        pointings_ecl=np.concatenate([part.pointings_ecl for part in parts]),
        detectors=detectors,
        start_time=first.start_time,
        flags=np.concatenate([part.flags for part in parts]),
        channel=channels.pop() if len(channels) == 1 else "",
        source=" + ".join(part.source for part in parts),
        orbit=first.orbit,
    )


def _read_recording(path: Path, memory_budget_bytes=None, samples=None) -> Recording:
    import h5py

    check_file(path)
    with h5py.File(path, "r") as handle:
        dataset, n_det, n_file, sampling_rate_hz = declared_layout(path, handle)
        pointings, hwp = handle["pointings"], handle["hwp_angle"]
        start, stop = (0, n_file) if samples is None else (int(samples[0]), int(samples[1]))
        if not 0 <= start < stop <= n_file or stop - start < MIN_SAMPLES:
            fail(
                path,
                f"samples {start}:{stop}: expected a range of at least {MIN_SAMPLES} samples "
                f"within the file's {n_file}",
            )
        n = stop - start
        check_memory(path, n_det, n, sampling_rate_hz, memory_budget_bytes)
        detectors = _read_detectors(path, dataset, n_det)
        start_time = _read_start_time(path, dataset)
        if start:
            start_time = start_time + astropy.time.TimeDelta(start / sampling_rate_hz, format="sec")
        tod = np.asarray(dataset[:, start:stop], dtype=float)
        pointings_ecl = np.asarray(pointings[:, start:stop], dtype=float)
        hwp_angle = np.asarray(hwp[start:stop], dtype=float)
        flags = _read_flags(path, handle, n_det, start, stop)

    mask_bad_samples(path, tod, pointings_ecl, hwp_angle, flags, detectors)
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


def mask_bad_samples(path, tod, pointings_ecl, hwp_angle, flags, detectors) -> None:
    """Mask, in place, the NaN samples of ``tod`` (n_det, n), ``pointings_ecl`` (n_det, n, 3)
    and ``hwp_angle`` (n,): their flags set and their values 0 (the HWP angle's bridged
    linearly); an Inf in an unflagged sample, or a detector without a valid sample, is a
    :class:`RecordingError` naming ``path``."""
    n_det, n = tod.shape
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
            fail(
                path,
                f"{int(unflagged.sum())} Inf value(s) in unflagged samples of {name!r} "
                f"(first: detector {k}, sample {i}); flag them or replace them by NaN",
            )
    nan_tod = ~np.isfinite(tod)
    nan_pointing = ~np.isfinite(pointings_ecl).all(axis=-1)
    nan_hwp = ~np.isfinite(hwp_angle)
    flags |= nan_tod | nan_pointing | nan_hwp[None, :]
    if flags.all():
        fail(path, "no valid sample: every sample is NaN or flagged")
    for k in range(n_det):
        if flags[k].all():
            fail(path, f"detector {detectors[k]['name']!r} has no valid sample (all NaN/flagged)")
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
    known = known_channels()
    if not channel or channel not in known:
        same = [name for name in known if name.lower() == channel.lower()]
        hint = f" (did you mean {same[0]!r}? names are case-sensitive)" if same else ""
        fail(
            recording.source,
            f"channel {channel!r} of detectors {recording.detector_names} is not in the "
            f"instrument model{hint}, so its nominal HWPSS amplitude is unknown: give it with "
            "--a2 A2_K (K_CMB; e.g. --a2 0.264), or write one of the model's channels in "
            f"the detectors' 'channel': {sorted(known)}",
        )
    return float(lookup(channel))


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
    observation = empty_observation(recording, detectors, "recorded TOD")
    observation.tod[:] = recording.tod
    return observation, False


def empty_observation(recording: Recording, detectors: list[dict], description: str):
    """A litebird_sim Observation of the recording's samples, start time and rate for
    ``detectors``, with one float64 K_CMB TOD ``tod`` (``description``), not filled."""
    import litebird_sim as lbs

    return lbs.Observation(
        detectors=detectors,
        n_samples_global=recording.n_samples,
        start_time_global=recording.start_time,
        sampling_rate_hz=recording.sampling_rate_hz,
        tods=[lbs.TodDescription("tod", lbs.Units.K_CMB, np.float64, description)],
    )


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
