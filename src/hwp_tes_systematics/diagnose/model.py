"""The nominal model of a recording and the context the catalog's forward models work on.

Nominal model (K_CMB), per detector k, for the recorded pointing and HWP angle chi:

    d_nom = I(p) + rho_k [Q(p) cos 2 a + U(p) sin 2 a] + D(t, p) + A_2 cos(2 (chi - theta_k)),
    a = 2 chi - theta_k + psi_gal,

with p the nearest pixel of the sky map (HEALPix RING, Galactic, nside of the map) to the
recorded pointing rotated from ecliptic to Galactic coordinates with
``lbs.rotate_coordinates_e2g``, theta_k the detector's polarisation angle, rho_k its
polarisation efficiency and D the orbital + solar dipole that litebird_sim computes
(``add_dipole_to_observations``, ``TOTAL_FROM_LIN_T``) from the start time and the
recorded pointing, with the spacecraft orbit tabulated exactly as
:class:`~hwp_tes_systematics.simulation.tod.PairSimulator` tabulates it (from one day before the
start, every hour), so that the dipole of a simulated recording is reproduced to
~1e-12 K. Scan, polarisation angle, HWPSS (``add_2f``), rotation, orbit and scanning
rates come from :mod:`data_model`, the module the simulation (``tod.py``) builds its
TOD from: one data model by construction.

The :class:`Context` holds these pieces per detector (sky intensity, sky polarisation,
dipole, HWPSS, the total d_nom, the other detector of the pair, the intensity seen
I(t) = I(p) + D, the HWP angle, the times and the valid-sample mask, and the change of
sky + dipole per arcmin of pointing offset along the focal plane's two axes): everything
the forward models of :mod:`.effects` need.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np

from ..simulation import data_model
from ..simulation.data_model import cache_litebird_sim_kernels, orbit_table
from .recording import empty_observation


def _spin_rate_hz() -> float:
    return data_model.scanning_rates_hz()[0]


def _precession_rate_hz() -> float:
    return data_model.scanning_rates_hz()[1]


class SkyMapError(ValueError):
    """The sky map given to the nominal model is not a (3, 12 nside^2) I, Q, U map."""


def check_sky_map(sky_iqu, source: str = "sky_iqu") -> np.ndarray:
    """Return the sky as a float (3, npix) array, or raise :class:`SkyMapError` naming ``source``."""
    sky = np.asarray(sky_iqu, dtype=float)
    if sky.ndim != 2 or sky.shape[0] != 3:
        raise SkyMapError(
            f"{source}: sky map of shape {sky.shape}; expected (3, 12 nside^2) = I, Q, U "
            "in K_CMB, HEALPix RING, Galactic"
        )
    npix = sky.shape[1]
    nside = round(np.sqrt(npix / 12))
    if nside < 1 or 12 * nside * nside != npix:
        raise SkyMapError(f"{source}: {npix} pixels per map is not 12 nside^2 for any nside")
    if not np.all(np.isfinite(sky)):
        bad = int(np.count_nonzero(~np.isfinite(sky)))
        raise SkyMapError(
            f"{source}: {bad} NaN/Inf pixel values (UNSEEN pixels must be filled before use)"
        )
    return sky


def load_sky(sky_iqu) -> tuple[np.ndarray, str]:
    """Accept an array or the path of a FITS map (read with ``sky.read_sky_map``)."""
    if isinstance(sky_iqu, (str, bytes)) or hasattr(sky_iqu, "__fspath__"):
        from ..sky import read_sky_map

        source = str(sky_iqu)
        try:
            values = read_sky_map(source)
        except Exception as error:  # healpy/astropy raise many types for a bad file
            raise SkyMapError(f"{source}: cannot read a sky map ({error})") from error
        return check_sky_map(values, source), source
    return check_sky_map(sky_iqu), "sky_iqu"


def partner_indices(n_detectors: int) -> np.ndarray:
    """Index of the other detector of each pair: (0, 1), (2, 3), ...; a lone detector is its own."""
    partner = np.arange(n_detectors) ^ 1
    partner[partner >= n_detectors] = np.arange(n_detectors)[partner >= n_detectors]
    return partner


@dataclass
class Context:
    """Nominal model pieces per detector, (n_det, n) arrays in K_CMB unless stated."""

    times_s: np.ndarray  # (n,) from the start of the recording
    sampling_rate_hz: float
    hwp_angle_rad: np.ndarray  # (n,) chi
    pol_angle_rad: np.ndarray  # (n_det,) theta_k
    pol_efficiency: np.ndarray  # (n_det,) rho_k
    sky_intensity: np.ndarray  # I(p)
    sky_polarization: np.ndarray  # rho (Q cos 2a + U sin 2a)
    dipole: np.ndarray  # D
    a2_k: np.ndarray  # (n_det,) A_2
    valid: np.ndarray  # (n_det, n) True where the sample is used
    detector_names: list[str]
    pixels: np.ndarray | None = None  # (n_det, n) Galactic RING pixels at the sky map's nside
    nside: int | None = None
    # rho (Q sin 2a - U cos 2a): d(sky_polarization)/d(theta) / 2 (pol-angle template)
    sky_polarization_quadrature: np.ndarray | None = None
    hwpss_phase_rad: np.ndarray | None = None  # (n_det,) phi: HWPSS A_2 cos(2 (chi - theta) - phi)
    adjustment: np.ndarray | None = None  # (n_det, n) fitted nominal adjustments (:mod:`.nominal`)
    # d(sky + dipole)/d(pointing offset) along the focal plane's x and y [K/arcmin], (n_det, 2, n)
    pointing_gradient: np.ndarray | None = None
    pointings_ecl: np.ndarray | None = None  # (n_det, n, 3) the recording's (theta, phi, psi)
    beam_arcmin: float = 30.0  # the detectors' beam FWHM (from their metadata, else MFT-like)
    f_spin_hz: float = field(default_factory=_spin_rate_hz)  # the IMo's scanning strategy
    f_precession_hz: float = field(default_factory=_precession_rate_hz)
    # {focal-plane key: each detector's group label} (:attr:`.recording.Recording.groups`)
    groups: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def n_detectors(self) -> int:
        return self.sky_intensity.shape[0]

    @property
    def n_samples(self) -> int:
        return self.times_s.size

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.sampling_rate_hz

    @cached_property
    def partner(self) -> np.ndarray:
        return partner_indices(self.n_detectors)

    @cached_property
    def detector_angle(self) -> np.ndarray:
        """chi - theta_k, (n_det, n)."""
        return self.hwp_angle_rad[None, :] - self.pol_angle_rad[:, None]

    @cached_property
    def hwpss_angle(self) -> np.ndarray:
        """x = 2 (chi - theta_k) - phi_k, the phase of the 2f HWPSS carrier, (n_det, n)."""
        angle = 2 * self.detector_angle
        if self.hwpss_phase_rad is not None:
            angle = angle - np.asarray(self.hwpss_phase_rad)[:, None]
        return angle

    @cached_property
    def carrier(self) -> np.ndarray:
        """cos x: the 2f HWPSS carrier of unit amplitude (:func:`data_model.hwpss`)."""
        return data_model.hwpss(self.hwp_angle_rad, self.pol_angle_rad, 1.0, self.hwpss_phase_rad)

    @cached_property
    def hwpss(self) -> np.ndarray:
        """A_2 cos(2 (chi - theta_k) - phi_k) (phi = 0 in the nominal model)."""
        return self.a2_k[:, None] * self.carrier

    @cached_property
    def sky(self) -> np.ndarray:
        return self.sky_intensity + self.sky_polarization

    @cached_property
    def intensity(self) -> np.ndarray:
        """I(t) = I(p) + D: the intensity the detector sees."""
        return self.sky_intensity + self.dipole

    @cached_property
    def d_nom(self) -> np.ndarray:
        """Total nominal TOD I + pol + D + A_2 cos(2 (chi - theta) - phi) (+ the adjustments)."""
        total = self.sky + self.dipole + self.hwpss
        if self.adjustment is not None:
            total = total + self.adjustment
        return total

    @cached_property
    def other(self) -> np.ndarray:
        """The other detector's nominal TOD, row k = d_nom of the partner of k."""
        return self.d_nom[self.partner]

    @cached_property
    def legendre_x(self) -> np.ndarray:
        """Time mapped to [-1, 1] over the recording: x = 2 (t - t0) / (t_end - t0) - 1."""
        span = self.times_s[-1] - self.times_s[0]
        if span <= 0:
            return np.zeros_like(self.times_s)
        return 2.0 * (self.times_s - self.times_s[0]) / span - 1.0

    def legendre(self, degree: int) -> np.ndarray:
        """P_degree(x) over the recording, (n,), by Bonnet's recursion (cached, read-only).

        (j + 1) P_{j+1} = (2 j + 1) x P_j - j P_{j-1}.
        """
        cache = self.extra.setdefault("legendre", [np.ones_like(self.legendre_x), self.legendre_x])
        x = self.legendre_x
        while len(cache) <= degree:
            j = len(cache) - 1
            cache.append(((2 * j + 1) * x * cache[j] - j * cache[j - 1]) / (j + 1))
        return cache[degree]

    @cached_property
    def f_hwp_hz(self) -> float:
        """HWP rotation frequency from the recorded angle (slope of the unwrapped chi)."""
        return hwp_frequency_hz(self.hwp_angle_rad, self.sampling_rate_hz)


def hwp_frequency_hz(hwp_angle_rad: np.ndarray, sampling_rate_hz: float) -> float:
    """f_HWP = slope of unwrap(chi) / 2 pi, by least squares over the whole recording."""
    chi = np.unwrap(np.asarray(hwp_angle_rad, dtype=float))
    if chi.size < 2:
        return 0.0
    t = np.arange(chi.size) / sampling_rate_hz
    slope = np.polyfit(t, chi, 1)[0]
    return float(abs(slope) / (2 * np.pi))


def dipole_tod(recording, pointings_ecl: np.ndarray | None = None) -> np.ndarray:
    """Orbital + solar dipole [K_CMB] at the recorded pointing (or at ``pointings_ecl``,
    (n_det, n, 3) ecliptic theta, phi, psi), (n_det, n) (litebird_sim), for the spacecraft
    velocity the recording carries (``recording.orbit``) or else litebird_sim's orbit."""
    import litebird_sim as lbs

    cache_litebird_sim_kernels()

    # litebird_sim's Observation wants a band centre; the total dipole (TOTAL_FROM_LIN_T)
    # does not depend on it, so a lab detector without one gets a placeholder
    detectors = [{"bandcenter_ghz": 100.0, **dict(det)} for det in recording.detectors]
    observation = empty_observation(recording, detectors, "dipole")
    observation.tod[:] = 0.0
    lbs.add_dipole_to_observations(
        observation,
        pos_and_vel=getattr(recording, "orbit", None)
        or orbit_table(recording.start_time, recording.duration_s),
        pointings=np.ascontiguousarray(
            recording.pointings_ecl if pointings_ecl is None else pointings_ecl
        ),
    )
    return np.array(observation.tod, dtype=float)


ARCMIN_RAD = np.pi / (180 * 60)
GRADIENT_STEP_ARCMIN = 1.0  # central difference of the dipole: its curvature error ~1e-8 relative


def unit_vectors(theta, phi):
    """n, e_theta, e_phi, (n, 3) each, at colatitude theta and longitude phi."""
    sin_t, cos_t, sin_p, cos_p = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    n = np.stack([sin_t * cos_p, sin_t * sin_p, cos_t], axis=-1)
    e_theta = np.stack([cos_t * cos_p, cos_t * sin_p, -sin_t], axis=-1)
    e_phi = np.stack([-sin_p, cos_p, np.zeros_like(phi)], axis=-1)
    return n, e_theta, e_phi


def focal_plane_axes(pointings_ecl: np.ndarray):
    """(n, u, v), (n, 3) each, ecliptic: the direction and the two tangent directions fixed
    in the focal plane, u = cos psi e_theta + sin psi e_phi, v = -sin psi e_theta + cos psi e_phi.

    A rotation of the detector quaternion by delta about the focal plane's x (y) axis
    (litebird_sim's pointing systematics, ``RotQuaternion(quat_rotation_x(delta)) * quat``)
    moves the pointing by delta along u (v), the same direction in the focal plane at every
    sample (checked to 1e-6 arcmin over half an hour: tests/diagnose/test_diagnose_pointing.py).
    """
    theta, phi, psi = pointings_ecl[:, 0], pointings_ecl[:, 1], pointings_ecl[:, 2]
    n, e_theta, e_phi = unit_vectors(theta, phi)
    cos_psi, sin_psi = np.cos(psi)[:, None], np.sin(psi)[:, None]
    return n, cos_psi * e_theta + sin_psi * e_phi, -sin_psi * e_theta + cos_psi * e_phi


def displaced_pointings(pointings_ecl: np.ndarray, axis: int, angle_rad) -> np.ndarray:
    """(n, 3) ecliptic pointings moved by ``angle_rad`` (scalar or (n,)) along u (axis 0)
    or v (axis 1) of :func:`focal_plane_axes`: n' = n cos delta + t sin delta, psi kept
    (one compiled pass per sample, no (n, 3) temporaries)."""
    pointings = np.ascontiguousarray(pointings_ecl, dtype=float)
    angles = np.ascontiguousarray(
        np.broadcast_to(np.asarray(angle_rad, dtype=float), pointings.shape[:1])
    )
    out = np.empty_like(pointings)
    _displace_kernel(pointings, int(axis), angles, out)
    return out


@numba.njit(cache=True, nogil=True)
def _displace_kernel(pointings, axis, angles, out):
    """out[t] = (theta', phi', psi) of n cos a + (u or v) sin a, as :func:`focal_plane_axes`."""
    for t in range(pointings.shape[0]):
        theta, phi, psi = pointings[t, 0], pointings[t, 1], pointings[t, 2]
        sin_t, cos_t, sin_p, cos_p = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
        cos_psi, sin_psi = np.cos(psi), np.sin(psi)
        if axis == 0:  # u = cos psi e_theta + sin psi e_phi
            a_theta, a_phi = cos_psi, sin_psi
        else:  # v = -sin psi e_theta + cos psi e_phi
            a_theta, a_phi = -sin_psi, cos_psi
        tx = a_theta * cos_t * cos_p - a_phi * sin_p
        ty = a_theta * cos_t * sin_p + a_phi * cos_p
        tz = -a_theta * sin_t
        cos_a, sin_a = np.cos(angles[t]), np.sin(angles[t])
        x = sin_t * cos_p * cos_a + tx * sin_a
        y = sin_t * sin_p * cos_a + ty * sin_a
        z = cos_t * cos_a + tz * sin_a
        out[t, 0] = np.arccos(min(max(z, -1.0), 1.0))
        out[t, 1] = np.mod(np.arctan2(y, x), 2 * np.pi)
        out[t, 2] = psi


def pointing_gradients(recording, sky: np.ndarray, threads: int = 1) -> np.ndarray:
    """d(sky + dipole)/d(offset) [K_CMB per arcmin], (n_det, 2, n): the signal's change
    when the pointing moves along u and v of :func:`focal_plane_axes` (a pointing offset
    about the focal plane's x and y axes), as central differences [S(+h) - S(-h)] / 2 h.

    Sky: I + rho (Q cos 2a + U sin 2a) at the nearest pixel of the map to the displaced
    directions (polarisation angle kept), h half a pixel: the nominal sky steps at pixel
    crossings, as a simulation scanning a map does, and the difference over +-h recovers an
    offset up to h without bias (beyond, as ~h; a smooth-gradient template underestimates a
    5 arcmin offset 3 to 10 times on an nside-32 map). Dipole (litebird_sim, smooth):
    h = 1 arcmin.
    """
    import ducc0

    nside = round(np.sqrt(sky.shape[1] / 12))
    healpix = ducc0.healpix.Healpix_Base(nside, "RING")
    half_pixel_rad = 0.5 * math.sqrt(4 * math.pi / sky.shape[1])
    chi = np.asarray(recording.hwp_angle_rad, dtype=float)
    step = GRADIENT_STEP_ARCMIN * ARCMIN_RAD
    n_det = recording.n_detectors
    out = np.empty((n_det, 2, recording.n_samples))
    for axis in (0, 1):
        ends = [
            np.stack(
                [
                    displaced_pointings(recording.pointings_ecl[k], axis, sign * step)
                    for k in range(n_det)
                ]
            )
            for sign in (1, -1)
        ]
        out[:, axis] = (dipole_tod(recording, ends[0]) - dipole_tod(recording, ends[1])) / (
            2 * GRADIENT_STEP_ARCMIN
        )
    for k in range(n_det):
        psi_gal = data_model.galactic_angles(recording.pointings_ecl[k])[:, 2]
        angles = data_model.polarisation_angles(
            chi, np.ascontiguousarray(psi_gal), recording.pol_angles_rad[k : k + 1]
        )
        rho = recording.pol_efficiency[k : k + 1]
        for axis in (0, 1):
            scanned = []
            for sign in (1, -1):
                moved = displaced_pointings(recording.pointings_ecl[k], axis, sign * half_pixel_rad)
                galactic = data_model.galactic_angles(moved)
                pixels = healpix.ang2pix(np.ascontiguousarray(galactic[:, :2]), nthreads=threads)
                scanned.append(data_model.scan(pixels[None, :], *angles, rho, sky)[0])
            out[k, axis] += (scanned[0] - scanned[1]) / (2 * half_pixel_rad / ARCMIN_RAD)
    return out


def scan_sky(recording, sky: np.ndarray, threads: int = 1):
    """(I(p), rho (Q cos 2a + U sin 2a), pixels, nside, rho (Q sin 2a - U cos 2a)).

    Values at the nearest pixel of the sky map; the last is the quadrature polarisation,
    d/d theta of the polarisation term = 2 rho (Q sin 2a - U cos 2a) (a = 2 chi - theta + psi).
    """
    import ducc0

    nside = round(np.sqrt(sky.shape[1] / 12))
    healpix = ducc0.healpix.Healpix_Base(nside, "RING")
    n_det, n = recording.n_detectors, recording.n_samples
    pixels = np.empty((n_det, n), dtype=np.int64)
    intensity = np.empty((n_det, n))
    polarization = np.empty((n_det, n))
    quadrature = np.empty((n_det, n))
    chi = np.asarray(recording.hwp_angle_rad, dtype=float)
    for k in range(n_det):
        galactic = data_model.galactic_angles(recording.pointings_ecl[k])
        pixels[k] = healpix.ang2pix(galactic[:, :2], nthreads=threads)
        angles = data_model.polarisation_angles(
            chi, np.ascontiguousarray(galactic[:, 2]), recording.pol_angles_rad[k : k + 1]
        )
        rho = recording.pol_efficiency[k : k + 1]
        row = pixels[k : k + 1]
        intensity[k] = sky[0][pixels[k]]
        polarization[k] = data_model.scan(row, *angles, rho, sky, intensity=False)[0]
        quadrature[k] = data_model.scan_quadrature(row, *angles, rho, sky)[0]
    return intensity, polarization, pixels, nside, quadrature


def per_detector(value, n_detectors: int, name: str) -> np.ndarray:
    """A scalar or one value per detector as a float (n_det,) array."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        return np.full(n_detectors, float(array))
    if array.shape != (n_detectors,):
        raise ValueError(f"{name}: {array.shape} values for {n_detectors} detectors")
    return array.copy()


def build_context(recording, sky_iqu, a2_k, threads: int = 1) -> Context:
    """Nominal model pieces of ``recording`` for the sky map ``sky_iqu`` and HWPSS A_2 [K]."""
    sky, _ = load_sky(sky_iqu)
    intensity, polarization, pixels, nside, quadrature = scan_sky(recording, sky, threads)
    a2 = per_detector(a2_k, recording.n_detectors, "a2_k")
    return Context(
        times_s=np.asarray(recording.times_s, dtype=float),
        sampling_rate_hz=float(recording.sampling_rate_hz),
        hwp_angle_rad=np.asarray(recording.hwp_angle_rad, dtype=float),
        pol_angle_rad=recording.pol_angles_rad,
        pol_efficiency=recording.pol_efficiency,
        sky_intensity=intensity,
        sky_polarization=polarization,
        dipole=dipole_tod(recording),
        a2_k=a2,
        valid=~np.asarray(recording.flags, dtype=bool),
        detector_names=recording.detector_names,
        pixels=pixels,
        nside=nside,
        sky_polarization_quadrature=quadrature,
        pointing_gradient=pointing_gradients(recording, sky, threads),
        pointings_ecl=recording.pointings_ecl,
        beam_arcmin=_beam_arcmin(recording),
        groups=recording.groups,
    )


def _beam_arcmin(recording) -> float:
    """The widest beam FWHM of the detectors' metadata [arcmin] (30 if none says)."""
    values = [float(d["fwhm_arcmin"]) for d in recording.detectors if d.get("fwhm_arcmin")]
    return max(values) if values else 30.0


def nominal_tod(recording, sky_iqu, a2_k) -> np.ndarray:
    """d_nom = sky + dipole + A_2 cos(2 (chi - theta)) at the recorded pointing, (n_det, n)."""
    return build_context(recording, sky_iqu, a2_k).d_nom


def coarse_pixels(ctx: Context, nside_out: int):
    """Galactic pixels at min(nside_out, the sky map's nside), RING, (n_det, n)."""
    import healpy as hp

    nside = ctx.nside
    if nside is None or ctx.pixels is None:
        return None, None
    if nside <= nside_out:
        return ctx.pixels, nside
    factor = round(math.log2(nside / nside_out))
    if 2**factor * nside_out != nside:
        return ctx.pixels, nside
    nest = hp.ring2nest(nside, ctx.pixels)
    return hp.nest2ring(nside_out, nest >> (2 * factor)), nside_out
