"""Time-ordered data of one detector pair, simulated chunk by chunk with litebird_sim.

For chunk k of the mission (plus a margin on each side for the notch filter) the
TOD of each detector, in K_CMB, is the paper's (the data model of :mod:`data_model`,
shared with the diagnosis's nominal model)

    d = I + rho [Q cos 2 alpha + U sin 2 alpha] + dipole + A_2 cos(2 (chi - theta_det)) + n,
    alpha = 2 chi - theta_det + psi       (ideal HWP; litebird_sim's convention)

with chi the HWP angle, theta_det the detector's polarisation angle and psi the
orientation in Galactic coordinates. litebird_sim gives the boresight attitude (PTEP
scanning strategy, phases counted from the mission start so chunks join up), the orbit
for the dipole (its ``TOTAL_FROM_LIN_T`` formula), the white + 1/f noise and the 2f
HWPSS (``add_2f``). The boresight quaternions, rotated once to Galactic coordinates, are
interpolated and composed with each direction's detector quaternion by ducc0's
``PointingProvider``; one kernel turns them into theta, phi, psi and the direction
vector (:func:`data_model.quaternion_pointing`), which the pixels, the angles, the sky
scans, the binning and the dipole all reuse. Tests check the pointing and the dipole
against litebird_sim's ``get_pointings`` and ``add_dipole``, and the scan against
``lbs.scan_map_in_observations``, to rounding.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import asdict, dataclass, field
from functools import cached_property

import astropy.time
import ducc0
import healpy as hp
import numpy as np

from .. import seeding
from ..instrument.channels import Channel, open_imo
from ..instrument.focal_plane import offset_quaternion
from ..sky.harmonics import BandLimitedSky
from . import data_model
from .data_model import cache_litebird_sim_kernels, ecliptic_to_galactic, orbit_table
from .hwpss_removal import harmonic_templates

log = logging.getLogger(__name__)

QUATERNION_STEP_S = 2.0  # spin-axis quaternion sampling (litebird_sim interpolates), ~1 arcsec


@dataclass(frozen=True)
class MissionPlan:
    """The observation: start, duration and the chunks it is processed in; with
    ``chunk_stride`` n > 1 only every n-th chunk is simulated (chunk index divisible by
    n: the mission sampled one chunk in n, each at its own time and pointing)."""

    start_time_tdb: str
    duration_s: float
    chunk_duration_s: float
    sampling_rate_hz: float
    chunk_stride: int = 1

    def __post_init__(self):
        if self.duration_s <= 0 or self.chunk_duration_s <= 0:
            raise ValueError(
                f"mission duration {self.duration_s} s and chunk {self.chunk_duration_s} s "
                "must be > 0"
            )
        if int(self.chunk_stride) != self.chunk_stride or self.chunk_stride < 1:
            raise ValueError(
                f"simulation.chunk_stride = {self.chunk_stride}: expected an integer >= 1"
            )

    @cached_property
    def start_time(self) -> astropy.time.Time:
        return astropy.time.Time(self.start_time_tdb, scale="tdb")

    @property
    def n_samples(self) -> int:
        return round(self.duration_s * self.sampling_rate_hz)

    @property
    def samples_per_chunk(self) -> int:
        return round(self.chunk_duration_s * self.sampling_rate_hz)

    def chunks(self) -> list[tuple[int, int, int]]:
        """(chunk index, first sample, number of samples) of the simulated chunks: every
        chunk of the mission, or every ``chunk_stride``-th."""
        step = self.samples_per_chunk
        return [
            (index, first, min(step, self.n_samples - first))
            for index, first in enumerate(range(0, self.n_samples, step))
            if index % self.chunk_stride == 0
        ]

    @property
    def simulated_samples(self) -> int:
        """Samples of the simulated chunks (the mission's ``n_samples`` when every chunk is)."""
        return sum(n for _, _, n in self.chunks())


class MissionScanningStrategy:
    """PTEP spinning strategy whose spin and precession phases count from the mission start.

    litebird_sim counts them from each simulation's own start; chunks simulated
    separately would then not join up.
    """

    def __init__(self, imo, release: str, mission_start: astropy.time.Time):
        import litebird_sim as lbs

        base = lbs.SpinningScanningStrategy.from_imo(
            imo, f"/releases/{release}/satellite/scanning_parameters"
        )
        self.strategy = base
        self.mission_start = mission_start

    def spin_to_ecliptic(self, start_time: astropy.time.Time, time_span_s: float):
        import litebird_sim as lbs
        from litebird_sim.scanning import interpolate_sun_earth_angles_rad

        n_quaternions = lbs.ScanningStrategy.optimal_num_of_quaternions(
            time_span_s=time_span_s, delta_time_s=QUATERNION_STEP_S
        )
        time_s = np.arange(n_quaternions) * QUATERNION_STEP_S
        offset_s = (start_time - self.mission_start).to("s").value
        quaternions = np.empty((n_quaternions, 4))
        self.strategy.all_spin_to_ecliptic(
            result_matrix=quaternions,
            sun_earth_angles_rad=interpolate_sun_earth_angles_rad(start_time, time_s),
            time_vector_s=offset_s + time_s,
        )
        return lbs.RotQuaternion(
            quats=quaternions, start_time=start_time, sampling_rate_hz=1.0 / QUATERNION_STEP_S
        )


NOISE_MODELS = {  # litebird_sim's 1/f models and the engine that draws each
    "toast": "fft",  # P(f) ~ (f^a + fk^a) / (f^a + fmin^a), drawn in Fourier space
    "keshner": "ducc",  # P(f) ~ ((f^2 + fk^2) / (f^2 + fmin^2))^(a/2), ducc0 OofaNoise
}


@dataclass
class ChunkPointing:
    """Pointing of one chunk (with margins): pixels and polarisation angles per detector.

    Detectors with one quaternion share one direction (the two of a pixel; in the PTEP
    model as shipped, every detector): ``galactic_rad`` holds one row per direction and
    ``direction_of`` says whose is whose. When all share one, ``pixels`` is a read-only
    broadcast of one row.
    """

    first_sample: int  # mission sample index of the first sample (negative in the margin)
    pixels: np.ndarray  # (n_det, n) RING pixel at the map nside
    cos_2alpha: np.ndarray  # (n_det, n)
    sin_2alpha: np.ndarray  # (n_det, n)
    hwp_angle_rad: np.ndarray  # (n,)
    galactic_rad: np.ndarray  # (n_directions, n, 3) theta, phi, psi in Galactic coordinates
    observation: object  # litebird_sim Observation, pointings prepared (ecliptic, lazy)
    direction_of: np.ndarray  # (n_det,) row of galactic_rad of each detector
    galactic_vectors: np.ndarray  # (n_directions, n, 3) unit direction vectors, Galactic
    _harmonic_templates: dict = field(default_factory=dict, init=False, repr=False)

    def ecliptic_rad(self) -> np.ndarray:
        """(n_det, n, 3) theta, phi, psi in ecliptic coordinates (litebird_sim, on demand)."""
        return self.observation.get_pointings("all")[0]

    def harmonic_templates(self, harmonics, offset: bool) -> np.ndarray:
        """D^T of the HWP-harmonic fit on this chunk
        (:func:`hwpss_removal.harmonic_templates`), computed once per (harmonics,
        offset): the chunk's filters share it (read-only)."""
        key = (tuple(harmonics), bool(offset))
        if key not in self._harmonic_templates:
            templates = harmonic_templates(self.hwp_angle_rad, *key)
            templates.flags.writeable = False
            self._harmonic_templates[key] = templates
        return self._harmonic_templates[key]


class PairSimulator:
    """Simulates the TOD of one channel's detector pair, chunk by chunk."""

    def __init__(
        self,
        channel: Channel,
        plan: MissionPlan,
        nside: int,
        imo_location: str | None = None,
        release: str = "vPTEP",
        threads: int = 1,
        noise_model: str = "toast",
    ):
        import litebird_sim as lbs

        cache_litebird_sim_kernels()
        if noise_model not in NOISE_MODELS:
            raise ValueError(f"noise model {noise_model!r}: expected one of {sorted(NOISE_MODELS)}")
        self.channel = channel
        self.plan = plan
        self.nside = nside
        self.threads = threads
        self.noise_model = noise_model
        imo = open_imo(imo_location)
        base = f"/releases/{release}/satellite/{channel.telescope}"
        self.instrument = lbs.InstrumentInfo.from_imo(imo, f"{base}/instrument_info")
        self.detectors = [
            lbs.DetectorInfo.from_imo(imo, f"{base}/{channel.name}/{name}/detector_info")
            for name in channel.detectors
        ]
        for detector, position in zip(
            self.detectors, channel.detector_positions or (), strict=False
        ):  # the focal-plane layout (the PTEP model points every detector at the boresight)
            detector.quat = lbs.RotQuaternion(quats=offset_quaternion(position))
        self.pol_angles_rad = np.array([d.pol_angle_rad for d in self.detectors])
        self.pol_efficiency = np.array([d.pol_efficiency for d in self.detectors])
        self.hwp_rad_per_s = self.instrument.hwp_rpm * 2 * np.pi / 60.0
        self._last_band_limited_scan = (None, None, None)  # sky, chunk, I Q U per direction
        self.scanning = MissionScanningStrategy(imo, release, plan.start_time)
        self.healpix = ducc0.healpix.Healpix_Base(nside, "RING")
        self.orbit = orbit_table(plan.start_time, plan.duration_s)
        rotation, _ = ecliptic_to_galactic()
        self.orbit_galactic = copy.copy(self.orbit)
        self.orbit_galactic.positions_km = self.orbit.positions_km @ rotation.T
        self.orbit_galactic.velocities_km_s = self.orbit.velocities_km_s @ rotation.T

    @classmethod
    def from_config(cls, config: dict, channel: Channel, plan: MissionPlan, nside: int, threads=1):
        """The simulator of ``channel`` with the configuration's instrument model and noise."""
        return cls(
            channel,
            plan,
            nside,
            config["instrument"]["imo_location"],
            config["instrument"]["imo_release"],
            threads,
            config["simulation"]["noise_model"],
        )

    @property
    def n_detectors(self) -> int:
        return len(self.detectors)

    @property
    def detector_names(self) -> list[str]:
        return [d.name for d in self.detectors]

    def _observation(self, detectors, start, n_samples):
        import litebird_sim as lbs

        return lbs.Observation(
            detectors=[asdict(d) for d in detectors],
            n_samples_global=n_samples,
            start_time_global=start,
            sampling_rate_hz=self.plan.sampling_rate_hz,
            tods=[lbs.TodDescription("tod", lbs.Units.K_CMB, np.float64, "total signal")],
        )

    def pointing(self, first_sample: int, n_samples: int) -> ChunkPointing:
        """Pointing for mission samples [first_sample, first_sample + n_samples).

        litebird_sim's PointingProvider computes theta, phi, psi directly in Galactic
        coordinates (the ecliptic -> Galactic rotation composed with the spin -> ecliptic
        quaternions), once per distinct detector direction; then for detector k
        2 alpha_k = 2 (2 chi + psi) - 2 theta_k by angle addition.
        """
        import litebird_sim as lbs

        sampling_rate_hz = self.plan.sampling_rate_hz
        offset_s = first_sample / sampling_rate_hz
        start = self.plan.start_time + astropy.time.TimeDelta(offset_s, format="sec")
        observation = self._observation(self.detectors, start, n_samples)
        spin2ecliptic = self.scanning.spin_to_ecliptic(
            start, n_samples / sampling_rate_hz + 2 * QUATERNION_STEP_S
        )
        hwp = lbs.IdealHWP(
            self.hwp_rad_per_s,
            start_angle_rad=float(np.mod(self.hwp_rad_per_s * offset_s, 2 * np.pi)),
        )
        lbs.prepare_pointings(
            observation, instrument=self.instrument, spin2ecliptic_quats=spin2ecliptic, hwp=hwp
        )
        bore2ecliptic = observation.pointing_provider.bore2ecliptic_quats
        bore2galactic = ecliptic_to_galactic()[1] * bore2ecliptic
        shape = (self.n_detectors, n_samples)
        direction_of = direction_groups(self.detectors)
        owners_of = [np.flatnonzero(direction_of == d) for d in range(direction_of.max() + 1)]
        hwp_angle = np.empty(n_samples)
        hwp.get_hwp_angle(
            output_buffer=hwp_angle, start_time_s=0.0, delta_time_s=1 / sampling_rate_hz
        )
        # ducc0 interpolates the boresight quaternions and composes each direction's
        # detector quaternion (litebird_sim's get_pointings does both in Python blocks)
        provider = ducc0.pointingprovider.PointingProvider(
            0.0, bore2galactic.sampling_rate_hz, bore2galactic.quats, self.threads
        )
        first_s = (start - bore2galactic.start_time).to_value("s")
        galactic = np.empty((len(owners_of), n_samples, 3))
        vectors = np.empty((len(owners_of), n_samples, 3))
        quaternions = np.empty((n_samples, 4))
        for direction, owners in enumerate(owners_of):
            detector_quaternion = observation.quat[owners[0]]
            if len(detector_quaternion.quats) > 1:  # time-dependent (a drifting pointing):
                # litebird_sim composes it with the boresight sample by sample
                lbs.PointingProvider(bore2galactic).get_pointings(
                    detector_quat=detector_quaternion,
                    start_time=start,
                    start_time_global=start,
                    sampling_rate_hz=sampling_rate_hz,
                    nsamples=n_samples,
                    pointing_buffer=galactic[direction],
                    compute_hwp_angle=False,
                )
                vectors[direction] = hp.ang2vec(
                    galactic[direction, :, 0], galactic[direction, :, 1]
                )
                continue
            provider.get_rotated_quaternions(
                first_s,
                sampling_rate_hz,
                detector_quaternion.quats[0],
                rot_left=False,
                out=quaternions,
            )
            data_model.quaternion_pointing(quaternions, galactic[direction], vectors[direction])
        del quaternions
        pixels = np.empty((len(owners_of), n_samples), dtype=np.int64)
        cos_2alpha = np.empty(shape)
        sin_2alpha = np.empty(shape)
        for direction, owners in enumerate(owners_of):
            pixels[direction] = self.healpix.ang2pix(
                galactic[direction, :, :2], nthreads=self.threads
            )
            first, last = owners[0], owners[-1] + 1
            if last - first == owners.size:  # a pixel's detectors are neighbours
                data_model.polarisation_angles(
                    hwp_angle,
                    galactic[direction, :, 2],
                    self.pol_angles_rad[owners],
                    cos_2alpha[first:last],
                    sin_2alpha[first:last],
                )
            else:
                cos_2alpha[owners], sin_2alpha[owners] = data_model.polarisation_angles(
                    hwp_angle, galactic[direction, :, 2], self.pol_angles_rad[owners]
                )
        if len(owners_of) == 1:
            pixels = np.broadcast_to(pixels, shape)
        else:
            pixels = pixels[direction_of]
        return ChunkPointing(
            first_sample,
            pixels,
            cos_2alpha,
            sin_2alpha,
            hwp_angle,
            galactic,
            observation,
            direction_of,
            vectors,
        )

    def pixels_at(
        self, pointing: ChunkPointing, nside: int, samples=slice(None), nest: bool = False
    ) -> np.ndarray:
        """(n_det, n) RING (or NESTED) pixels of the ``samples`` of a chunk at any
        resolution, from the same directions (``pointing.pixels``: RING, own nside)."""
        if nside == self.nside and not nest:
            return pointing.pixels[:, samples]
        healpix = ducc0.healpix.Healpix_Base(nside, "NEST" if nest else "RING")
        pixels = np.stack(
            [
                healpix.ang2pix(np.ascontiguousarray(direction[samples, :2]), nthreads=self.threads)
                for direction in pointing.galactic_rad
            ]
        )
        if len(pixels) == 1:
            return np.broadcast_to(pixels, (self.n_detectors, pixels.shape[1]))
        return pixels[pointing.direction_of]

    def scan_sky(self, pointing: ChunkPointing, sky_iqu_k, out=None) -> np.ndarray:
        """I + rho (Q cos 2 alpha + U sin 2 alpha) [K_CMB], (n_det, n), written to ``out``
        if given: of a (3, npix) map at the nearest pixel, or of a
        :class:`sky.harmonics.BandLimitedSky` at each sample's direction."""
        if isinstance(sky_iqu_k, BandLimitedSky):
            if out is None:
                out = np.empty(pointing.cos_2alpha.shape)
            # the same sky scanned again on the same chunk (the fixed pass's foreground
            # and its reference): the evaluation is most of the cost, so the last is kept
            # (the sky itself is held, so that a new one is never taken for it)
            chunk = (pointing.first_sample, pointing.hwp_angle_rad.size)
            last_sky, last_chunk, values = self._last_band_limited_scan
            if last_sky is not sky_iqu_k or last_chunk != chunk:
                values = [sky_iqu_k.at(direction[:, :2]) for direction in pointing.galactic_rad]
                self._last_band_limited_scan = (sky_iqu_k, chunk, values)
            for k, direction in enumerate(pointing.direction_of):
                i, q, u = values[direction]
                rho = self.pol_efficiency[k]
                out[k] = i + rho * (q * pointing.cos_2alpha[k] + u * pointing.sin_2alpha[k])
            return out
        return data_model.scan(
            pointing.pixels,
            pointing.cos_2alpha,
            pointing.sin_2alpha,
            self.pol_efficiency,
            sky_iqu_k,
            out,
        )

    def dipole(self, pointing: ChunkPointing) -> np.ndarray:
        """Orbital + solar dipole [K_CMB] (litebird_sim's TOTAL_FROM_LIN_T), (n_det, n).

        Evaluated in Galactic coordinates (directions and spacecraft velocity rotated
        alike), from each direction's unit vectors (:func:`data_model.dipole_total_from_lin_t`;
        litebird_sim's ``add_dipole`` recomputes them from theta and phi, 3 times the
        cost); the velocity is litebird_sim's interpolation of the orbit. The dipole
        depends on the direction only, so detectors sharing one get one computation."""
        velocities = self.orbit_galactic.compute_velocities(
            time0=pointing.observation.start_time,
            delta_time_s=1 / self.plan.sampling_rate_hz,
            num_of_samples=pointing.hwp_angle_rad.size,
        )
        owners = np.unique(pointing.direction_of, return_index=True)[1]  # first of each
        per_direction = np.stack(
            [
                data_model.dipole_total_from_lin_t(
                    vectors, velocities, self.detectors[owner].bandcenter_ghz
                )
                for owner, vectors in zip(owners, pointing.galactic_vectors, strict=True)
            ]
        )
        return per_direction[pointing.direction_of]  # (n_det, n), a copy

    def hwpss(self, pointing: ChunkPointing, amplitude_k: float) -> np.ndarray:
        """A_2 cos(2 (chi - theta_det)) [K_CMB] via litebird_sim's add_2f, (n_det, n)."""
        return data_model.hwpss(pointing.hwp_angle_rad, self.pol_angles_rad, float(amplitude_k))

    def noise(
        self, pointing: ChunkPointing, master_seed: int, seed: int, chunk: int, scale: float = 1.0
    ):
        """White + 1/f noise [K_CMB] from the detector NET, fknee, alpha (litebird_sim's
        ``add_noise``, model ``self.noise_model``), times ``scale`` (1 = the instrument
        model's noise). One stream per (master seed, channel, seed, chunk, detector)."""
        from litebird_sim.noise import add_noise

        tod = np.zeros((self.n_detectors, pointing.hwp_angle_rad.size))
        generators = [
            seeding.rng(master_seed, "noise", self.channel.name, seed, chunk, name)
            for name in self.detector_names
        ]

        def values(key):
            return np.array([getattr(d, key) for d in self.detectors], dtype=float)

        add_noise(
            tod,
            "one_over_f",
            self.plan.sampling_rate_hz,
            values("net_ukrts"),
            values("fknee_mhz"),
            values("fmin_hz"),
            values("alpha"),
            generators,
            scale=scale,
            engine=NOISE_MODELS[self.noise_model],
            model=self.noise_model,
        )
        return tod


def direction_groups(detectors) -> np.ndarray:
    """(n_det,) the direction of each detector, numbered in order of first appearance:
    detectors with equal quaternions (the two of one pixel) share one."""
    quats = [np.asarray(d.quat.quats, dtype=float) for d in detectors]
    firsts: list[int] = []
    direction_of = np.empty(len(quats), dtype=np.int64)
    for k, q in enumerate(quats):
        same = [
            j
            for j, f in enumerate(firsts)
            if quats[f].shape == q.shape and np.array_equal(quats[f], q)
        ]
        if same:
            direction_of[k] = same[0]
        else:
            direction_of[k] = len(firsts)
            firsts.append(k)
    return direction_of
