"""Time-ordered data of one detector pair, simulated chunk by chunk with litebird_sim.

For chunk k of the mission (plus a margin on each side for the notch filter) the
TOD of each detector, in K_CMB, is the paper's

    d = I + rho [Q cos 2 alpha + U sin 2 alpha] + dipole + A_2 cos(2 (chi - theta_det)) + n,
    alpha = 2 chi - theta_det + psi       (ideal HWP; litebird_sim's convention)

with chi the HWP angle, theta_det the detector's polarisation angle and psi the
orientation in Galactic coordinates. litebird_sim gives the pointing (PTEP
scanning strategy, phases counted from the mission start so chunks join up), the
orbital + solar dipole (one orbit for the whole mission), the white + 1/f noise and
the 2f HWPSS (``add_2f``). The pointing is computed once per chunk, rotated once to
Galactic coordinates and its pixels and angles reused for scanning the sky and for
binning; a test checks the scan against ``lbs.scan_map_in_observations``.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from functools import cached_property

import astropy.time
import ducc0
import numpy as np

from . import seeding
from .instrument import Channel, open_imo

log = logging.getLogger(__name__)

QUATERNION_STEP_S = 2.0  # spin-axis quaternion sampling (litebird_sim interpolates), ~1 arcsec
ORBIT_STEP_S = 3600.0  # spacecraft position/velocity sampling for the dipole


@dataclass(frozen=True)
class MissionPlan:
    """The observation: start, duration and the chunks it is processed in."""

    start_time_tdb: str
    duration_s: float
    chunk_duration_s: float
    sampling_rate_hz: float

    def __post_init__(self):
        if self.duration_s <= 0 or self.chunk_duration_s <= 0:
            raise ValueError(
                f"mission duration {self.duration_s} s and chunk {self.chunk_duration_s} s "
                "must be > 0"
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
        """(chunk index, first sample, number of samples) covering the mission."""
        step = self.samples_per_chunk
        return [
            (index, first, min(step, self.n_samples - first))
            for index, first in enumerate(range(0, self.n_samples, step))
        ]


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


@dataclass
class ChunkPointing:
    """Pointing of one chunk (with margins): pixels and polarisation angles per detector."""

    first_sample: int  # mission sample index of the first sample (negative in the margin)
    pixels: np.ndarray  # (n_det, n) RING pixel at the map nside
    cos_2alpha: np.ndarray  # (n_det, n)
    sin_2alpha: np.ndarray  # (n_det, n)
    hwp_angle_rad: np.ndarray  # (n,)
    observation: object  # the litebird_sim Observation (ecliptic pointings precomputed)


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
    ):
        import litebird_sim as lbs

        self.channel = channel
        self.plan = plan
        self.nside = nside
        self.threads = threads
        imo = open_imo(imo_location)
        base = f"/releases/{release}/satellite/{channel.telescope}"
        self.instrument = lbs.InstrumentInfo.from_imo(imo, f"{base}/instrument_info")
        self.detectors = [
            lbs.DetectorInfo.from_imo(imo, f"{base}/{channel.name}/{name}/detector_info")
            for name in channel.detector_pair
        ]
        self.pol_angles_rad = np.array([d.pol_angle_rad for d in self.detectors])
        self.pol_efficiency = np.array([d.pol_efficiency for d in self.detectors])
        self.hwp_rad_per_s = self.instrument.hwp_rpm * 2 * np.pi / 60.0
        self.scanning = MissionScanningStrategy(imo, release, plan.start_time)
        self.healpix = ducc0.healpix.Healpix_Base(nside, "RING")
        margin_days = 2.0  # the orbit table must cover the filter margins before and after
        self.orbit = lbs.spacecraft_pos_and_vel(
            lbs.SpacecraftOrbit(
                plan.start_time - astropy.time.TimeDelta(86400 * margin_days / 2, format="sec")
            ),
            start_time=plan.start_time
            - astropy.time.TimeDelta(86400 * margin_days / 2, format="sec"),
            time_span_s=plan.duration_s + 86400 * margin_days,
            delta_time_s=ORBIT_STEP_S,
        )

    @property
    def n_detectors(self) -> int:
        return len(self.detectors)

    @property
    def detector_names(self) -> list[str]:
        return [d.name for d in self.detectors]

    def pointing(self, first_sample: int, n_samples: int) -> ChunkPointing:
        """Pointing for mission samples [first_sample, first_sample + n_samples)."""
        import litebird_sim as lbs

        sampling_rate_hz = self.plan.sampling_rate_hz
        offset_s = first_sample / sampling_rate_hz
        start = self.plan.start_time + astropy.time.TimeDelta(offset_s, format="sec")
        observation = lbs.Observation(
            detectors=[asdict(d) for d in self.detectors],
            n_samples_global=n_samples,
            start_time_global=start,
            sampling_rate_hz=sampling_rate_hz,
            tods=[lbs.TodDescription("tod", lbs.Units.K_CMB, np.float64, "total signal")],
        )
        quaternions = self.scanning.spin_to_ecliptic(
            start, n_samples / sampling_rate_hz + 2 * QUATERNION_STEP_S
        )
        hwp = lbs.IdealHWP(
            self.hwp_rad_per_s,
            start_angle_rad=float(np.mod(self.hwp_rad_per_s * offset_s, 2 * np.pi)),
        )
        lbs.prepare_pointings(
            observation, instrument=self.instrument, spin2ecliptic_quats=quaternions, hwp=hwp
        )
        lbs.precompute_pointings(observation)
        hwp_angle = np.asarray(observation.hwp_angle, dtype=float)
        pixels = np.empty((self.n_detectors, n_samples), dtype=np.int64)
        cos_2alpha = np.empty((self.n_detectors, n_samples))
        sin_2alpha = np.empty((self.n_detectors, n_samples))
        for index in range(self.n_detectors):
            galactic = lbs.rotate_coordinates_e2g(observation.pointing_matrix[index])
            pixels[index] = self.healpix.ang2pix(galactic[:, :2], nthreads=self.threads)
            alpha = 2 * hwp_angle - self.pol_angles_rad[index] + galactic[:, 2]
            cos_2alpha[index] = np.cos(2 * alpha)
            sin_2alpha[index] = np.sin(2 * alpha)
        return ChunkPointing(first_sample, pixels, cos_2alpha, sin_2alpha, hwp_angle, observation)

    def scan_sky(self, pointing: ChunkPointing, sky_iqu_k: np.ndarray) -> np.ndarray:
        """I + rho (Q cos 2 alpha + U sin 2 alpha) at the nearest pixel [K_CMB], (n_det, n)."""
        i_map, q_map, u_map = sky_iqu_k
        pix = pointing.pixels
        rho = self.pol_efficiency[:, None]
        return i_map[pix] + rho * (
            q_map[pix] * pointing.cos_2alpha + u_map[pix] * pointing.sin_2alpha
        )

    def dipole(self, pointing: ChunkPointing) -> np.ndarray:
        """Orbital + solar dipole [K_CMB] (litebird_sim, TOTAL_FROM_LIN_T), (n_det, n)."""
        import litebird_sim as lbs

        observation = pointing.observation
        observation.tod[:] = 0.0
        lbs.add_dipole_to_observations(observation, pos_and_vel=self.orbit)
        return observation.tod.copy()

    def hwpss(self, pointing: ChunkPointing, amplitude_k: float) -> np.ndarray:
        """A_2 cos(2 (chi - theta_det)) [K_CMB] via litebird_sim's add_2f, (n_det, n)."""
        from litebird_sim.hwp_diff_emiss import add_2f

        tod = np.zeros((self.n_detectors, pointing.hwp_angle_rad.size))
        if amplitude_k != 0.0:
            add_2f(
                tod,
                pointing.hwp_angle_rad,
                self.pol_angles_rad,
                np.full(self.n_detectors, float(amplitude_k)),
            )
        return tod

    def noise(
        self, pointing: ChunkPointing, master_seed: int, seed: int, chunk: int, scale: float = 1.0
    ):
        """White + 1/f noise [K_CMB] from the detector NET, fknee, alpha (litebird_sim),
        times ``scale`` (1 = the instrument model's noise)."""
        import litebird_sim as lbs

        observation = pointing.observation
        observation.tod[:] = 0.0
        generators = [
            seeding.rng(master_seed, "noise", self.channel.name, seed, chunk, name)
            for name in self.detector_names
        ]
        lbs.add_noise_to_observations(
            observation, "one_over_f", dets_random=generators, scale=scale
        )
        return observation.tod.copy()
