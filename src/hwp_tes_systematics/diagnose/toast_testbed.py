"""Recordings written by TOAST 3's own operators, none of this package's simulator, for the
tests of :mod:`.toast_recording` and ``benchmarks/diagnose_toast.py`` (needs the ``toast``
extra).

A LiteBIRD scan (``SimSatellite``: spin 20 min at 50 deg, precession 192.348 min at 45 deg,
a HWP), the sky map scanned by ``ScanHealpixMap`` through ``StokesWeights`` with the HWP,
TOAST's dipole (``SimDipole``, total), gain drift (``GainDrifter``), noise
(``DefaultNoiseModel`` + ``SimNoise``) and cosmic rays (``InjectCosmicRays``), saved by
``SaveHDF5``. The pointing's frame is
Galactic by default: ``ScanHealpixMap`` scans the map in the pointing's frame.

The HWPSS, the nonlinearity and a constant gain have no TOAST operator; they are added to
the observation's signal here, as a TOAST user would:

    d -> (1 + g) [(1 + g1 d') d'],   d' = d + A_2 cos(2 (omega - gamma) - phi),

with omega the HWP angle and gamma the focal plane's ``gamma``. ``net_written_factor``
scales the NET written in the file's focal plane after the noise is drawn (the nominal
noise off by that factor); ``flagged_fraction`` flags random stretches of every detector.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np


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
    hwpss_phase_rad: float = 0.0,
    g1_per_k: float = 0.0,
    gain: float = 0.0,
    gain_drift_sigma: float = 0.0,
    gain_drift_mode: str = "linear_drift",
    gain_drift_mismatch: float = 1.0,
    wafers: int = 1,
    use_pixels: int | None = None,
    thermal_drift: tuple[float, float] = (0.0, 0.0),
    thermal_drift_common_to: str = "wafer",
    crosstalk: dict | None = None,
    common_mode: tuple[float, float, str] | None = None,
    cosmic_rays: dict | None = None,
    readout_steps: list | None = None,
    dipole: bool = True,
    noise: bool = True,
    net_uk_rts: float | list = 50.0,
    fknee_mhz: float = 20.0,
    net_written_factor: float = 1.0,
    flagged_fraction: float = 0.0,
    edit=None,
    truth: dict | None = None,
    start: datetime = datetime(2032, 4, 1, tzinfo=UTC),
) -> Path:
    """Write one TOAST observation of ``2 n_pixels`` detectors (``n_pixels`` 1, 7, 19: a
    hexagon) into ``folder``; return the file's path. ``wafers``: the pixels split in that
    many groups of consecutive pixels, a ``wafer`` column of the focal plane;
    ``use_pixels``: only the hexagon's first that many pixels (32 of 37: 64 detectors). The gain
    drift is GainDrifter's ``gain_drift_mode`` ("linear_drift", or "slow_drift": a 1/f
    stream below 0.2 mHz, ``gain_drift_mismatch`` its part per detector and the rest
    common to a wafer). ``edit(data)`` is called on the ``toast.Data`` just before it is
    saved; ``truth`` (a dict) receives each detector's gain g(t) GainDrifter applied: the
    end of the ramp g - 1 as ``gain_drift_slope`` and its Legendre coefficients over the
    recording (unweighted) as ``gain_drift_mean`` (P0) and ``gain_drift_legendre``
    (P1..P3); ``start``: the observation's start (UTC). ``crosstalk``: {(i, j): c_ij},
    TOAST's ``CrossTalk`` adding c_ij of detector j's TOD (signal and noise) to detector
    i's, i and j indices in the focal plane's order. ``thermal_drift``: GainDrifter's
    ``thermal_drift`` (a bath temperature fluctuating as 1/f up to Nyquist, TOAST's
    defaults: fknee 20 mHz, alpha 1, 1 K per K over a 100 mK bath) twice, its
    ``sigma_drift`` [K] for a stream common to each wafer (each pixel with one wafer; with
    ``thermal_drift_common_to`` "all", to all detectors) and for a stream of each
    detector's own: the gain's common part has the power fraction
    rho = s_w^2 / (s_w^2 + s_d^2). ``common_mode``: (NET [uK sqrt(s)], knee [mHz], key),
    TOAST's ``CommonModeNoise`` (alpha 1, coupling 1) adding to the noise model a noise
    common to the detectors of each value of the focal-plane column ``key`` ("wafer",
    "pixel", or "all" for every detector), drawn by ``SimNoise`` with the rest.
    ``net_uk_rts``: one NET for all detectors, or one per detector in the focal plane's
    order. ``cosmic_rays``: TOAST's ``InjectCosmicRays`` (:func:`_cosmic_rays`), keys
    ``event_rate_hz`` (direct hits per detector), ``hits`` ({"c1", "c2", "tau_ms"}: draws
    of the hits' C1 + C2 exp(-t / tau) [K, K, ms], which TOAST resamples), ``wafer_noise_k``
    (the white wafer noise's mean and rms per sample [K]) and ``pair_correlation`` (its
    part common to each pixel's two detectors, or None), optionally ``shared`` ({"by":
    a focal-plane column or "all", "scale": a factor per detector}: each group's detectors
    take its first detector's hits times their factor, coincident hits);
    ``truth["cosmic_ray_hits"]`` receives each detector's hits as [first sample, samples,
    peak K]. ``readout_steps``: [(detector index, first sample, offset K, gain), ...], each
    detector's TOD (signal and noise, after the hits) d -> d + H(t - t_s) (o + s d)
    (:func:`_readout_steps`; TOAST has no such operator), into
    ``truth["readout_steps"]`` as {detector: [[first sample, offset, gain], ...]}."""
    import astropy.units as u
    from toast import ops
    from toast.observation import default_values as defaults

    focalplane = _focalplane(
        n_pixels, sample_rate_hz, np.mean(net_uk_rts), fknee_mhz, wafers, use_pixels
    )
    data = _satellite_scan(focalplane, start, hours, hwp_rpm, coord)
    pointing = ops.PointingDetectorSimple(boresight=defaults.boresight_radec)
    pixels = ops.PixelsHealpix(nside=_nside(sky_fits), detector_pointing=pointing)
    weights = ops.StokesWeights(
        mode="IQU", hwp_angle=defaults.hwp_angle, detector_pointing=pointing
    )
    ops.ScanHealpixMap(file=str(sky_fits), pixel_pointing=pixels, stokes_weights=weights).apply(
        data
    )
    if dipole:
        ops.SimDipole(mode="total", coord=coord).apply(data)
    observation = data.obs[0]
    _add_response(observation, a2_k, hwpss_phase_rad, g1_per_k, gain)
    if gain_drift_sigma:
        group = "wafer" if wafers > 1 else "pixel"  # what slow_drift's common part follows
        drifter = (gain_drift_mode, gain_drift_sigma, gain_drift_mismatch, group, seed)
        _drift_gains(data, drifter, truth)
    if any(thermal_drift):
        _thermal_drifts(data, thermal_drift, thermal_drift_common_to, wafers, seed)
    if noise:
        if np.ndim(net_uk_rts):  # one NET per detector, as the noise model reads them
            table = observation.telescope.focalplane.detector_data
            table["psd_net"] = np.asarray(net_uk_rts) * 1e-6 * u.K * np.sqrt(1 * u.s)
        ops.DefaultNoiseModel().apply(data)
        if common_mode is not None:
            _common_mode(data, *common_mode)
        ops.SimNoise(realization=seed).apply(data)
    if cosmic_rays is not None:
        _cosmic_rays(data, cosmic_rays, seed, truth)
    if readout_steps:
        _readout_steps(data, readout_steps, truth)
    ops.Delete(detdata=[pixels.pixels, weights.weights, pointing.quats]).apply(data)
    if crosstalk:
        _crosstalk(data, crosstalk, Path(folder))
    if net_written_factor != 1.0:
        table = observation.telescope.focalplane.detector_data
        table["psd_net"] = table["psd_net"] * net_written_factor
    if flagged_fraction:
        _flag_stretches(observation, flagged_fraction, np.random.default_rng(seed))
    if edit is not None:
        edit(data)
    folder = Path(folder)
    ops.SaveHDF5(volume=str(folder)).apply(data)
    return next(folder.glob("obs_*.h5"))


def _satellite_scan(focalplane, start, hours: float, hwp_rpm: float, coord: str):
    """A ``toast.Data`` with one observation of SimSatellite's LiteBIRD scan and a HWP."""
    import astropy.units as u
    import toast
    from toast import ops
    from toast.instrument import SpaceSite, Telescope
    from toast.observation import default_values as defaults
    from toast.schedule_sim_satellite import create_satellite_schedule

    schedule = create_satellite_schedule(
        prefix="obs_",
        mission_start=start,
        observation_time=hours * u.hour,
        gap_time=0 * u.minute,
        num_observations=1,
        prec_period=192.348 * u.minute,
        spin_period=20 * u.minute,
    )
    data = toast.Data(toast.Comm())
    ops.SimSatellite(
        name="satellite",
        telescope=Telescope("litebird", focalplane=focalplane, site=SpaceSite("L2")),
        schedule=schedule,
        hwp_angle=defaults.hwp_angle,
        hwp_rpm=hwp_rpm,
        spin_angle=50 * u.deg,
        prec_angle=45 * u.deg,
        coord=coord,
    ).apply(data)
    return data


def _focalplane(n_pixels, sample_rate_hz, net_uk_rts, fknee_mhz, wafers: int, use_pixels=None):
    """TOAST's hexagon of ``n_pixels`` pixels, 5 deg wide, 140 GHz, 30 arcmin (its first
    ``use_pixels`` pixels only, if given); with ``wafers`` > 1 a ``wafer`` column: the
    pixels split in that many consecutive groups."""
    import astropy.units as u
    from toast.instrument import Focalplane
    from toast.instrument_sim import fake_hexagon_focalplane

    focalplane = fake_hexagon_focalplane(
        n_pix=n_pixels,
        sample_rate=sample_rate_hz * u.Hz,
        psd_fmin=1e-5 * u.Hz,
        psd_net=net_uk_rts * 1e-6 * u.K * np.sqrt(1 * u.s),
        psd_fknee=fknee_mhz * 1e-3 * u.Hz,
        width=5 * u.deg,
        bandcenter=140 * u.GHz,
        fwhm=30 * u.arcmin,
    )
    if use_pixels is not None and use_pixels < n_pixels:
        table = focalplane.detector_data
        kept = set(_pixel_names(table)[:use_pixels])
        rows = np.array([str(p) in kept for p in table["pixel"]])
        focalplane = Focalplane(detector_data=table[rows], sample_rate=sample_rate_hz * u.Hz)
    if wafers > 1:
        table = focalplane.detector_data
        pixel_names = _pixel_names(table)
        wafer_of = {p: f"W{i * wafers // len(pixel_names)}" for i, p in enumerate(pixel_names)}
        table["wafer"] = [wafer_of[str(p)] for p in table["pixel"]]
    return focalplane


def _pixel_names(table) -> list[str]:
    """The focal plane table's pixels, in their order of first appearance."""
    return list(dict.fromkeys(str(p) for p in table["pixel"]))


def _add_response(observation, a2_k, hwpss_phase_rad, g1_per_k, gain) -> None:
    """signal -> (1 + gain) (1 + g1 d') d', d' = signal + A_2 cos(2 (omega - gamma) - phi)."""
    import astropy.units as u
    from toast.observation import default_values as defaults

    signal = observation.detdata[defaults.det_data]
    hwp = np.asarray(observation.shared[defaults.hwp_angle].data)
    focalplane = observation.telescope.focalplane
    for name in observation.local_detectors:
        gamma = focalplane[name]["gamma"].to_value(u.rad)
        total = signal[name] + a2_k * np.cos(2 * (hwp - gamma) - hwpss_phase_rad)
        signal[name][:] = (1 + gain) * (1 + g1_per_k * total) * total


def _drift_gains(data, drifter: tuple, truth: dict | None) -> None:
    """TOAST's GainDrifter on the signal, ``drifter`` its (drift_mode, sigma_drift,
    detector_mismatch, focalplane_group, realization); each detector's gain g(t) into
    ``truth`` (the same draw on a unit stream: the draw is keyed by the detector's uid and
    group, not by the data's name)."""
    from toast import ops
    from toast.observation import default_values as defaults

    traits = ("drift_mode", "sigma_drift", "detector_mismatch", "focalplane_group", "realization")
    drifter = dict(zip(traits, drifter, strict=True))

    observation = data.obs[0]
    for name in ("unit_gain", defaults.det_data):
        observation.detdata.ensure(name, dtype=np.float64)
        if name == "unit_gain":
            observation.detdata[name][:] = 1.0
        ops.GainDrifter(det_data=name, **drifter).apply(data)
    gains = observation.detdata["unit_gain"]
    if truth is not None:
        x = np.linspace(-1.0, 1.0, observation.n_local_samples)
        basis = np.stack([np.polynomial.legendre.Legendre.basis(j)(x) for j in range(4)])
        truth["gain_drift_slope"] = {}
        truth["gain_drift_mean"] = {}
        truth["gain_drift_legendre"] = {}
        for name in observation.local_detectors:
            drift = np.asarray(gains[name]) - 1.0
            coefficients = np.linalg.lstsq(basis.T, drift, rcond=None)[0]
            truth["gain_drift_slope"][name] = float(drift[-1])
            truth["gain_drift_mean"][name] = float(coefficients[0])
            truth["gain_drift_legendre"][name] = coefficients[1:].tolist()
    ops.Delete(detdata=["unit_gain"]).apply(data)


def _thermal_drifts(data, sigmas, common_to: str, wafers: int, seed: int) -> None:
    """GainDrifter's thermal_drift twice: ``sigmas`` [K] of a stream common to each wafer
    (each pixel with one wafer; to every detector with ``common_to`` "all") and of a stream
    of each detector's own."""
    from toast import ops

    common = "pixel" if common_to == "wafer" and wafers == 1 else _group_column(data, common_to)
    for component, (group, sigma) in enumerate(zip((common, "name"), sigmas, strict=True)):
        if sigma:
            ops.GainDrifter(
                drift_mode="thermal_drift",
                sigma_drift=sigma,
                detector_mismatch=0.0,
                focalplane_group=group,
                realization=seed,
                component=1 + component,
            ).apply(data)


def _group_column(data, key: str) -> str:
    """The focal-plane column whose values group the detectors: ``key``, or for "all" a
    column of one value added to the table."""
    if key != "all":
        return key
    data.obs[0].telescope.focalplane.detector_data["focalplane"] = "FP"
    return "focalplane"


def _crosstalk(data, couplings: dict, folder: Path) -> None:
    """TOAST's CrossTalk with the matrix of ``couplings`` (written as its .npz file)."""
    from toast import ops

    detectors = data.obs[0].telescope.focalplane.detectors
    matrix = np.zeros((len(detectors), len(detectors)))
    for (i, j), value in couplings.items():
        matrix[i, j] = value
    path = folder / "crosstalk_matrix.npz"
    np.savez(path, matrix=matrix)
    ops.CrossTalk(xtalk_mat_file=str(path)).apply(data)
    path.unlink()


def _common_mode(data, net_uk_rts: float, fknee_mhz: float, key: str) -> None:
    """TOAST's CommonModeNoise on the noise model: a noise common to each ``key`` group."""
    import astropy.units as u
    from toast import ops

    ops.CommonModeNoise(
        focalplane_key=_group_column(data, key),
        fmin=1e-5 * u.Hz,
        fknee=fknee_mhz * 1e-3 * u.Hz,
        alpha=1.0,
        NET=net_uk_rts * 1e-6 * u.K * u.s**0.5,
    ).apply(data)


MAX_HIT_DRAWS = 50  # InjectCosmicRays fails on a detector drawn without a hit: drawn again


def _cosmic_rays(data, rays: dict, seed: int, truth: dict | None) -> None:
    """TOAST's InjectCosmicRays twice. First the direct hits alone (its wafer noise set to
    0) into a stream of their own, whose runs of nonzero samples are each detector's hits
    (the truth), added to the signal; then the white wafer noise, with its part common to
    each pixel's two detectors, on the signal (another realization). Its data files (one
    per detector: ``low_noise``, ``sampling_rate`` 1 kHz, ``direct_hits``,
    ``correlation_matrix``) are in W with a conversion of 1 K/W: amplitudes in K."""
    import tempfile

    import astropy.units as u
    from toast import ops
    from toast.observation import default_values as defaults

    observation = data.obs[0]
    n_det = len(observation.local_detectors)
    hits = np.column_stack([np.asarray(rays["hits"][key], float) for key in ("c1", "c2", "tau_ms")])
    pair_correlation = rays.get("pair_correlation")
    correlation = np.eye(n_det)
    for k in range(0, n_det - 1, 2):  # InjectCosmicRays pairs detectors 2k and 2k + 1
        correlation[k, k + 1] = correlation[k + 1, k] = pair_correlation or 0.0
    signal = observation.detdata[defaults.det_data]
    # InjectCosmicRays names a detector's file by replacing "detector" in the whole path
    with tempfile.TemporaryDirectory(prefix="toast_cosmic_rays_") as folder:
        for part, low_noise in enumerate(((0.0, 0.0), tuple(rays["wafer_noise_k"]))):
            for k in range(n_det):
                np.savez(
                    Path(folder) / f"part{part}_det{k}.npz",
                    low_noise=np.asarray(low_noise, float),
                    sampling_rate=np.array([1000.0]),
                    direct_hits=hits,
                    correlation_matrix=correlation,
                )
            if part == 0 and not rays["event_rate_hz"]:
                continue
            stream = "cosmic_ray_hits" if part == 0 else defaults.det_data
            observation.detdata.ensure(stream, dtype=np.float64)
            injector = ops.InjectCosmicRays(
                det_data=stream,
                crfile=str(Path(folder) / f"part{part}_detector.npz"),
                crdata_units=u.W,
                conversion_factor=1.0 * u.K / u.W,
                eventrate=rays["event_rate_hz"],
                inject_direct_hits=part == 0,
                include_common_mode=part == 1 and pair_correlation is not None,
                realization=seed + 1000 * part,
            )
            for attempt in range(MAX_HIT_DRAWS):
                # its Poisson count of hits draws from numpy's global state, and a detector
                # drawn without a hit fails its assertions (a max over no hits)
                np.random.seed([seed, part, attempt])
                try:
                    injector.apply(data)
                    break
                except ValueError:
                    if part == 1 or attempt == MAX_HIT_DRAWS - 1:
                        raise
                    observation.detdata[stream][:] = 0.0
            if part == 0:
                injected = observation.detdata[stream]
                if rays.get("shared"):
                    _share_hits(data, injected, rays["shared"])
                found = {}
                for name in observation.local_detectors:
                    signal[name][:] += injected[name]
                    found[name] = _hits(np.asarray(injected[name]))
                if truth is not None:
                    truth["cosmic_ray_hits"] = found
                ops.Delete(detdata=[stream]).apply(data)


def _readout_steps(data, steps, truth: dict | None) -> None:
    """Each step (detector index, first sample, offset [K], gain) on the detector's whole
    TOD from its first sample: d -> d + o + s d (a SQUID's flux jump, a bias step)."""
    from toast.observation import default_values as defaults

    observation = data.obs[0]
    names = list(observation.local_detectors)
    signal = observation.detdata[defaults.det_data]
    injected: dict[str, list] = {}
    for detector, first, offset_k, gain in steps:
        if not (0 <= int(detector) < len(names) and 0 < int(first) < observation.n_local_samples):
            raise ValueError(
                f"readout_steps: step ({detector}, {first}) outside {len(names)} detectors "
                f"and {observation.n_local_samples} samples"
            )
        tod = signal[names[int(detector)]]
        tod[int(first) :] += offset_k + gain * tod[int(first) :]
        injected.setdefault(names[int(detector)], []).append([int(first), offset_k, gain])
    if truth is not None:
        truth["readout_steps"] = injected


def _share_hits(data, injected, shared: dict) -> None:
    """Coincident hits: every detector of a group (``shared["by"]``: a focal-plane column,
    or "all") takes the hits TOAST drew for the group's first detector, times its own
    ``shared["scale"]`` (one factor per detector, in the focal plane's order; a hit's
    energy deposited differs from detector to detector)."""
    observation = data.obs[0]
    names = list(observation.local_detectors)
    scale = np.asarray(shared["scale"], float)
    if scale.shape != (len(names),):
        raise ValueError(
            f"cosmic_rays.shared.scale: {scale.size} factors for {len(names)} detectors"
        )
    table = observation.telescope.focalplane.detector_data
    column = _group_column(data, shared["by"])
    group_of = {str(row["name"]): str(row[column]) for row in table}
    first: dict[str, np.ndarray] = {}
    for k, name in enumerate(names):
        group = group_of[name]
        if group not in first:
            first[group] = np.array(injected[name], dtype=float)
        injected[name][:] = scale[k] * first[group]


def _hits(stream: np.ndarray) -> list[list]:
    """[first sample, samples, peak] of each run of nonzero samples of ``stream``."""
    nonzero = np.concatenate([[False], stream != 0.0, [False]])
    edges = np.flatnonzero(np.diff(nonzero.astype(np.int8)))
    out = []
    for first, stop in zip(edges[::2], edges[1::2], strict=True):
        piece = stream[first:stop]
        out.append([int(first), int(stop - first), float(piece[np.argmax(np.abs(piece))])])
    return out


def _flag_stretches(observation, fraction: float, rng, n_stretches: int = 4) -> None:
    """Flag (invalid) ``n_stretches`` random stretches of each detector, ``fraction`` in all."""
    n = observation.n_local_samples
    length = max(1, int(fraction * n / n_stretches))
    for name in observation.local_detectors:
        flags = observation.detdata["flags"][name]
        for start in rng.integers(0, n - length, n_stretches):
            flags[start : start + length] |= 1


def _nside(sky_fits) -> int:
    import healpy as hp

    return hp.get_nside(hp.read_map(str(sky_fits), field=0, dtype=np.float64))
