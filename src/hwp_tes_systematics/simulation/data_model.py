"""The TOD data model, written once: the simulation (:class:`tod.PairSimulator`) and the
diagnosis's nominal model (:mod:`diagnose.model`) both build their TODs from here.

Per detector k, in K_CMB,

    d_k = I(p) + rho_k [Q(p) cos 2 alpha + U(p) sin 2 alpha] + D + A_2 cos(2 (chi - theta_k)),
    alpha = 2 chi - theta_k + psi          (ideal HWP; litebird_sim's convention)

with p the nearest HEALPix (RING, Galactic) pixel, chi the HWP angle, theta_k the
detector's polarisation angle, psi the pointing's orientation in Galactic coordinates
and D the orbital + solar dipole (litebird_sim, from :func:`orbit_table`). The scanning
rates, the ecliptic -> Galactic rotation and the HWPSS (``add_2f``) are litebird_sim's.
"""

from __future__ import annotations

import functools

import astropy.time
import numba
import numpy as np

ORBIT_STEP_S = 3600.0  # spacecraft position/velocity sampling for the dipole
ORBIT_MARGIN_S = 86400.0  # orbit table from one day before to one day after (filter margins)


@functools.cache
def cache_litebird_sim_kernels() -> int:
    """Turn on numba's on-disk cache for litebird_sim's compiled kernels.

    litebird_sim compiles its numba kernels (pointing, HWP angle, dipole, add_2f, ...)
    in every new process without caching them: ~10-25 s per process, more than a
    one-day pair takes to simulate. With the cache, only the first process of an
    installation compiles. Returns the number of kernels switched to caching.
    """
    import sys

    import litebird_sim  # noqa: F401 (loads the modules whose kernels are cached)
    from numba.core.registry import CPUDispatcher

    kernels = {
        id(obj): obj
        for name, module in list(sys.modules.items())
        if name.startswith("litebird_sim") and module is not None
        for obj in vars(module).values()
        if isinstance(obj, CPUDispatcher)
    }
    for kernel in kernels.values():
        kernel.enable_caching()
    return len(kernels)


@functools.lru_cache(maxsize=4)
def scanning_rates_hz(imo_location: str | None = None, release: str = "vPTEP"):
    """(spin, precession) rates [Hz] of the instrument model's scanning strategy
    (PTEP: 0.05 rpm, one turn per 192.348 min)."""
    import litebird_sim as lbs

    from ..instrument.channels import open_imo

    strategy = lbs.SpinningScanningStrategy.from_imo(
        open_imo(imo_location), f"/releases/{release}/satellite/scanning_parameters"
    )
    return float(strategy.spin_rate_hz), float(strategy.precession_rate_hz)


def orbit_table(start_time: astropy.time.Time, duration_s: float):
    """Spacecraft position and velocity (litebird_sim, ecliptic) every ORBIT_STEP_S from
    ORBIT_MARGIN_S before ``start_time`` to ORBIT_MARGIN_S after the end: the table the
    dipole of the simulation and of the diagnosis's nominal model is computed from."""
    import litebird_sim as lbs

    orbit_start = start_time - astropy.time.TimeDelta(ORBIT_MARGIN_S, format="sec")
    return lbs.spacecraft_pos_and_vel(
        lbs.SpacecraftOrbit(orbit_start),
        start_time=orbit_start,
        time_span_s=duration_s + 2 * ORBIT_MARGIN_S,
        delta_time_s=ORBIT_STEP_S,
    )


@functools.cache
def ecliptic_to_galactic():
    """The ecliptic -> Galactic rotation of litebird_sim: (3x3 matrix, RotQuaternion)."""
    import litebird_sim as lbs
    from scipy.spatial.transform import Rotation

    matrix = np.asarray(lbs.coordinates.ECL_TO_GAL_ROT_MATRIX, dtype=float)
    # litebird_sim quaternions are (x, y, z, w), as scipy's
    return matrix, lbs.RotQuaternion(quats=Rotation.from_matrix(matrix).as_quat())


def galactic_angles(pointings_ecliptic_rad: np.ndarray) -> np.ndarray:
    """(theta, phi, psi) in Galactic coordinates from ecliptic ones, (n, 3)
    (litebird_sim's ``rotate_coordinates_e2g``: the same rotation as
    :func:`ecliptic_to_galactic`, on angles)."""
    import litebird_sim as lbs

    return lbs.rotate_coordinates_e2g(np.ascontiguousarray(pointings_ecliptic_rad))


def quaternion_pointing(quaternions: np.ndarray, angles_out=None, vectors_out=None):
    """(theta, phi, psi) [rad] and the unit direction vector of detector-to-sky rotation
    quaternions (n, 4), components (x, y, z, w): the direction is the rotated z axis
    v = R z, the orientation psi the angle of R x from the local North towards East
    (litebird_sim's ``compute_pointing_and_orientation``, to rounding; its North and East
    written with v's components instead of the sines and cosines of theta and phi).
    Written into ``angles_out`` (n, 3) and ``vectors_out`` (n, 3) if given."""
    n = np.shape(quaternions)[0]
    angles_out = np.empty((n, 3)) if angles_out is None else angles_out
    vectors_out = np.empty((n, 3)) if vectors_out is None else vectors_out
    _quaternion_pointing_kernel(quaternions, angles_out, vectors_out)
    return angles_out, vectors_out


def dipole_total_from_lin_t(vectors, velocities_km_s, frequency_ghz: float, out=None):
    """Orbital + solar dipole [K_CMB] at unit directions n (n, 3) with the spacecraft
    velocity v (n, 3) [km/s]: litebird_sim's ``TOTAL_FROM_LIN_T``,

        dT = T_0 / f(x) [N(x gamma (1 - beta . n)) / N(x) - 1],   x = h nu / (k_B T_0),

    N(x) = 1 / (e^x - 1), f(x) = x e^x / (e^x - 1), beta = v / c; the same operations
    as litebird_sim's kernel, from the direction vector rather than (theta, phi)."""
    from litebird_sim.constants import C_LIGHT_KM_OVER_S, H_OVER_K_B, T_CMB_K

    out = np.empty(np.shape(vectors)[0]) if out is None else out
    h_nu_over_k = H_OVER_K_B * frequency_ghz * 1e9
    x = h_nu_over_k / T_CMB_K
    f_x = x * np.exp(x) / (np.exp(x) - 1)
    _dipole_kernel(
        vectors,
        velocities_km_s,
        h_nu_over_k,
        T_CMB_K,
        C_LIGHT_KM_OVER_S,
        1 / np.expm1(x),
        f_x,
        out,
    )
    return out


def polarisation_angles(hwp_angle_rad, psi_rad, pol_angles_rad, cos_2alpha=None, sin_2alpha=None):
    """cos 2 alpha_k, sin 2 alpha_k (n_det, n) for detectors of polarisation angles
    theta_k sharing one pointing orientation psi (n,): 2 alpha = 2 (2 chi + psi) - 2 theta_k.
    Written into ``cos_2alpha``, ``sin_2alpha`` if given."""
    pol_angles_rad = np.asarray(pol_angles_rad, dtype=float)
    shape = (pol_angles_rad.size, np.shape(hwp_angle_rad)[0])
    if cos_2alpha is None:
        cos_2alpha, sin_2alpha = np.empty(shape), np.empty(shape)
    _polarisation_angle_kernel(hwp_angle_rad, psi_rad, pol_angles_rad, cos_2alpha, sin_2alpha)
    return cos_2alpha, sin_2alpha


def scan(pixels, cos_2alpha, sin_2alpha, rho, sky_iqu_k, out=None, intensity: bool = True):
    """I[p] + rho_k (Q[p] cos 2 alpha + U[p] sin 2 alpha), (n_det, n) [units of the map];
    ``intensity`` False leaves out I (the polarisation term alone)."""
    if out is None:
        out = np.empty(np.shape(cos_2alpha))
    i_map, q_map, u_map = (np.ascontiguousarray(m, dtype=float) for m in sky_iqu_k)
    rho = np.ascontiguousarray(rho, dtype=float)
    _scan_kernel(pixels, cos_2alpha, sin_2alpha, rho, i_map, q_map, u_map, intensity, out)
    return out


def scan_quadrature(pixels, cos_2alpha, sin_2alpha, rho, sky_iqu_k):
    """rho_k (Q[p] sin 2 alpha - U[p] cos 2 alpha) = d(polarisation term)/d(theta_k) / 2:
    the polarisation term of the map (0, -U, Q)."""
    _, q_map, u_map = sky_iqu_k
    rotated = (np.zeros_like(q_map), -np.asarray(u_map), q_map)
    return scan(pixels, cos_2alpha, sin_2alpha, rho, rotated, intensity=False)


def hwpss(hwp_angle_rad, pol_angles_rad, amplitudes_k, phases_rad=None) -> np.ndarray:
    """A_k cos(2 (chi - theta_k) - phi_k) [K_CMB], (n_det, n), through litebird_sim's
    ``add_2f`` (a phase phi_k is the offset theta_k + phi_k / 2). ``amplitudes_k``: one
    value or one per detector; ``phases_rad``: None (the nominal model: 0) or one per detector."""
    from litebird_sim.hwp_diff_emiss import add_2f

    offsets = np.asarray(pol_angles_rad, dtype=float)
    if phases_rad is not None:
        offsets = offsets + 0.5 * np.asarray(phases_rad, dtype=float)
    amplitudes = np.broadcast_to(np.asarray(amplitudes_k, dtype=float), offsets.shape)
    tod = np.zeros((offsets.size, np.shape(hwp_angle_rad)[0]))
    if np.any(amplitudes != 0.0):
        add_2f(tod, np.asarray(hwp_angle_rad, dtype=float), offsets, amplitudes.copy())
    return tod


@numba.njit(cache=True, nogil=True)
def _polarisation_angle_kernel(hwp_angle, psi, pol_angles, cos_2alpha, sin_2alpha):
    """cos, sin of 2 alpha_k = 2 (2 chi + psi) - 2 theta_k for each detector k, by angle
    addition from the theta = 0 angle (one cos and one sin per sample)."""
    cos_theta = np.cos(2 * pol_angles)
    sin_theta = np.sin(2 * pol_angles)
    for t in range(hwp_angle.size):
        twice_alpha0 = 2 * (2 * hwp_angle[t] + psi[t])
        cos0 = np.cos(twice_alpha0)
        sin0 = np.sin(twice_alpha0)
        for k in range(pol_angles.size):
            cos_2alpha[k, t] = cos0 * cos_theta[k] + sin0 * sin_theta[k]
            sin_2alpha[k, t] = sin0 * cos_theta[k] - cos0 * sin_theta[k]


@numba.njit(cache=True, nogil=True)
def _scan_kernel(pixels, cos_2alpha, sin_2alpha, rho, i_map, q_map, u_map, intensity, out):
    """out[k, t] = I[p] (if ``intensity``) + rho_k (Q[p] cos 2 alpha + U[p] sin 2 alpha)."""
    for det in range(out.shape[0]):
        for t in range(out.shape[1]):
            p = pixels[det, t]
            value = rho[det] * (q_map[p] * cos_2alpha[det, t] + u_map[p] * sin_2alpha[det, t])
            out[det, t] = i_map[p] + value if intensity else value


@numba.njit(cache=True, nogil=True)
def _quaternion_pointing_kernel(quaternions, angles, vectors):
    """theta, phi, psi and v = R z per quaternion (see :func:`quaternion_pointing`)."""
    for t in range(quaternions.shape[0]):
        qx, qy, qz, qw = quaternions[t, 0], quaternions[t, 1], quaternions[t, 2], quaternions[t, 3]
        x = 2 * (qw * qy + qx * qz)  # R z
        y = 2 * (qy * qz - qw * qx)
        z = 1 - 2 * (qx * qx + qy * qy)
        ox = 1 - 2 * (qy * qy + qz * qz)  # R x, the orientation
        oy = 2 * (qx * qy + qw * qz)
        oz = 2 * (qx * qz - qw * qy)
        r = np.sqrt(x * x + y * y)  # sin theta; East = (-y, x, 0) / r
        cos_psi = min(max((-y * ox + x * oy) / r, -1.0), 1.0)  # R x . East
        sin_psi = min(max(-z * (x * ox + y * oy) / r + r * oz, -1.0), 1.0)  # R x . North
        angles[t, 0] = np.arctan2(r, z)
        angles[t, 1] = np.arctan2(y, x)
        angles[t, 2] = np.arctan2(sin_psi, cos_psi)
        vectors[t, 0], vectors[t, 1], vectors[t, 2] = x, y, z


@numba.njit(cache=True, nogil=True)
def _dipole_kernel(vectors, velocities, h_nu_over_k, t_cmb_k, c_km_s, n_x, f_x, out):
    """out[t] = T_0 / f_x (N(x') / N(x) - 1), x' = h nu gamma (1 - beta . n) / (k T_0)."""
    for t in range(out.size):
        vx, vy, vz = velocities[t, 0], velocities[t, 1], velocities[t, 2]
        beta_dot_n = (vectors[t, 0] * vx + vectors[t, 1] * vy + vectors[t, 2] * vz) / c_km_s
        beta = np.sqrt(vx**2 + vy**2 + vz**2) / c_km_s
        gamma = 1 / np.sqrt(1 - beta**2)
        x_doppler = h_nu_over_k * gamma * (1 - beta_dot_n) / t_cmb_k
        out[t] = t_cmb_k / f_x * ((1 / np.expm1(x_doppler)) / n_x - 1)
