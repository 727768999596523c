"""Figures of the diagnosis: residual spectrum, residual versus HWP angle, time series, map."""

from __future__ import annotations

import numpy as np

from ...figures import save_figure, subplots
from ...simulation.spectral import amplitude_spectrum
from ..effects import CATALOG

MAX_POINTS = 20000
MAX_PANELS = 8  # detectors drawn per figure; a wafer shows the ones the fit changed most


def panel_detectors(before, after, valid, at_most: int = MAX_PANELS) -> list[int]:
    """The detectors a figure draws, in recording order: all if at most ``at_most``, else
    the ``at_most`` whose residual the fit changed most, sum_t (before^2 - after^2) over
    the valid samples in units of the residual's own variance after the fit."""
    n_det = before.shape[0]
    if n_det <= at_most:
        return list(range(n_det))
    change = np.empty(n_det)
    for k in range(n_det):
        b, a = before[k][valid[k]], after[k][valid[k]]
        if a.size == 0:  # every sample flagged: nothing to draw
            change[k] = -np.inf
            continue
        change[k] = (np.sum(b * b) - np.sum(a * a)) / max(float(np.var(a)), 1e-300)
    return sorted(np.argsort(-change, kind="stable")[:at_most].tolist())


def _title(ctx, detectors, what: str) -> str:
    """A figure's title: what it shows, and which detectors when not all of them."""
    n_det = len(ctx.detector_names)
    if len(detectors) == n_det:
        return what
    return f"{what}: {len(detectors)} of {n_det} detectors, those the fit changed most"


def _max_decimate(x: np.ndarray, y: np.ndarray, n_out: int = MAX_POINTS):
    """Keep the largest y per chunk so that lines survive the decimation."""
    if x.size <= n_out:
        return x, y
    chunk = int(np.ceil(x.size / n_out))
    n = (x.size // chunk) * chunk
    yc = y[:n].reshape(-1, chunk)
    index = np.argmax(yc, axis=1) + np.arange(yc.shape[0]) * chunk
    return x[index], y[index]


def plot_residual_spectrum(ctx, before, after, noise_models, lines, path, detectors) -> None:
    """Amplitude spectra of the residual before and after the fit, per detector."""
    n_panels = len(detectors)
    fig, axes = subplots(n_panels, 1, figsize=(9, 3.2 * n_panels), squeeze=False)
    fig.suptitle(_title(ctx, detectors, "residual spectrum"), fontsize=10)
    for k, ax in zip(detectors, axes[:, 0], strict=True):
        freqs, amp_before = amplitude_spectrum(before[k], ctx.sampling_rate_hz)
        _, amp_after = amplitude_spectrum(after[k], ctx.sampling_rate_hz)
        keep = freqs > 0
        x, y = _max_decimate(freqs[keep], amp_before[keep])
        ax.loglog(x, y, lw=0.5, label="residual before the fit")
        x, y = _max_decimate(freqs[keep], amp_after[keep])
        ax.loglog(x, y, lw=0.5, alpha=0.8, label="after the fit")
        duration = ctx.duration_s
        noise_amp = np.sqrt(noise_models[k].psd(freqs[keep]) / duration)
        ax.loglog(freqs[keep], noise_amp, color="k", lw=0.8, label="noise (1 sigma line amplitude)")
        strongest = {}
        for line in lines:
            if line["detector"] == ctx.detector_names[k]:
                label = line["identification"]
                if label not in strongest or line["amplitude_before_k"] > strongest[label][1]:
                    strongest[label] = (line["freq_hz"], line["amplitude_before_k"])
        for label, (freq, amplitude) in strongest.items():
            ax.annotate(label, (freq, amplitude), fontsize=7, rotation=45)
        ax.set_title(ctx.detector_names[k], fontsize=9)
        ax.set_ylabel("amplitude [K]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    axes[-1, 0].set_xlabel("frequency [Hz]")
    save_figure(fig, path)


def plot_hwp_profile(ctx, profiles_before, profiles_after, path, detectors) -> None:
    """Residual averaged in bins of the HWP angle, before and after the fit."""
    n_panels = len(detectors)
    fig, axes = subplots(n_panels, 1, figsize=(8, 2.8 * n_panels), squeeze=False, sharex=True)
    fig.suptitle(_title(ctx, detectors, "residual versus HWP angle"), fontsize=10)
    for k, ax in zip(detectors, axes[:, 0], strict=True):
        name = ctx.detector_names[k]
        centres, profile, sigma = profiles_before[name]
        ax.errorbar(np.degrees(centres), 1e6 * profile, 1e6 * sigma, fmt=".", ms=3, label="before")
        centres, profile, sigma = profiles_after[name]
        ax.errorbar(np.degrees(centres), 1e6 * profile, 1e6 * sigma, fmt=".", ms=3, label="after")
        ax.set_ylabel("residual [uK]")
        ax.set_title(name, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("HWP angle chi [deg]")
    save_figure(fig, path)


def _block_mean(times, values, valid, n_blocks=2000):
    n = times.size
    size = max(1, n // n_blocks)
    m = (n // size) * size
    v = np.where(valid, values, 0.0)[:m].reshape(-1, size)
    w = valid[:m].reshape(-1, size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return times[:m].reshape(-1, size).mean(axis=1), v.sum(axis=1) / w.sum(axis=1)


def plot_residual_timeseries(ctx, before, after, events, path, detectors) -> None:
    """Residual versus time (block means), with the glitches found."""
    n_panels = len(detectors)
    fig, axes = subplots(n_panels, 1, figsize=(9, 2.8 * n_panels), squeeze=False, sharex=True)
    fig.suptitle(_title(ctx, detectors, "residual versus time"), fontsize=10)
    for k, ax in zip(detectors, axes[:, 0], strict=True):
        t, m = _block_mean(ctx.times_s, before[k], ctx.valid[k])
        ax.plot(t / 3600, 1e6 * m, lw=0.6, label=f"before (means over {t[1] - t[0]:.3g} s)")
        t, m = _block_mean(ctx.times_s, after[k], ctx.valid[k])
        ax.plot(t / 3600, 1e6 * m, lw=0.6, label="after")
        for e in events:
            if e["detector"] == k:
                ax.axvline(e["time_s"] / 3600, color="r", lw=0.6, alpha=0.6)
        ax.set_ylabel("residual [uK]")
        ax.set_title(ctx.detector_names[k], fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [h]  (red: glitches)")
    save_figure(fig, path)


def plot_residual_map(residual_map, nside, path, title="residual map") -> None:
    """Mollweide view of the binned residual (Galactic)."""
    import healpy as hp

    projector = hp.projector.MollweideProj(xsize=800)
    values = np.where(np.isfinite(residual_map), residual_map, hp.UNSEEN)
    image = projector.projmap(values, lambda x, y, z: hp.vec2pix(nside, x, y, z))
    image = np.ma.masked_where((image == hp.UNSEEN) | ~np.isfinite(image), image)
    fig, ax = subplots(figsize=(8, 4.5))
    finite = image.compressed()
    limit = np.percentile(np.abs(finite), 99) * 1e6 if finite.size else 1.0
    shown = ax.imshow(1e6 * image, origin="lower", cmap="RdBu_r", vmin=-limit, vmax=limit)
    ax.set_axis_off()
    ax.set_title(f"{title} (Galactic, nside {nside})", fontsize=9)
    fig.colorbar(shown, ax=ax, orientation="horizontal", fraction=0.05, label="uK")
    save_figure(fig, path)


def diagnosis_figures(
    out_dir, ctx, residual, residual_after, mismatch, noise_models, result
) -> dict:
    """All figures; returns {title: file name}."""
    from ..locate import hwp_profile, sky_residual

    files = {}
    detectors = panel_detectors(residual, residual_after, np.asarray(ctx.valid, dtype=bool))
    plot_residual_spectrum(
        ctx,
        residual,
        residual_after,
        noise_models,
        result["lines"],
        out_dir / "residual_spectrum.png",
        detectors,
    )
    files["residual spectrum before/after"] = "residual_spectrum.png"
    after_profiles = {}
    for k in detectors:
        name = ctx.detector_names[k]
        sigma = noise_models[k].net_k_sqrt_s * np.sqrt(ctx.sampling_rate_hz)
        centres, profile, err, _ = hwp_profile(residual_after[k], ctx, k, sigma)
        after_profiles[name] = (centres, profile, err)
    plot_hwp_profile(
        ctx, mismatch.profiles, after_profiles, out_dir / "residual_vs_hwp_angle.png", detectors
    )
    files["residual versus HWP angle"] = "residual_vs_hwp_angle.png"
    events = []
    for effect in result["effects"]:
        if getattr(CATALOG.get(effect["name"]), "events", False):  # the times of its events
            for p in effect["parameters"].values():
                if p["parameter"] == "time":
                    events.append(
                        {"detector": ctx.detector_names.index(p["detector"]), "time_s": p["value"]}
                    )
    plot_residual_timeseries(
        ctx, residual, residual_after, events, out_dir / "residual_time.png", detectors
    )
    files["residual time series"] = "residual_time.png"
    if mismatch.sky.get("available") and "residual_map" in mismatch.sky:
        plot_residual_map(
            mismatch.sky["residual_map"], mismatch.sky["nside"], out_dir / "residual_map.png"
        )
        files["residual map (before the fit)"] = "residual_map.png"
        sigma = np.array([m.net_k_sqrt_s * np.sqrt(ctx.sampling_rate_hz) for m in noise_models])
        after_sky = sky_residual(residual_after, ctx, sigma)
        if "residual_map" in after_sky:
            plot_residual_map(
                after_sky["residual_map"],
                after_sky["nside"],
                out_dir / "residual_map_after.png",
                title="residual map after the fit",
            )
            files["residual map (after the fit)"] = "residual_map_after.png"
    return files
