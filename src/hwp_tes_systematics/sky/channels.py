"""The sky seen by one channel: CMB realisation + band-integrated foregrounds, beam-smoothed."""

from __future__ import annotations

from ..instrument.radiometry import channel_bandpass
from .cmb import cmb_map
from .foregrounds import foreground_map, foreground_source


def channel_sky_map(
    channel,
    nside: int,
    lmax: int,
    r: float,
    master_seed: int,
    seed: int,
    pysm_local_data=None,
    single_mode: bool = True,
) -> dict:
    """The sky seen by a channel, RING, Galactic, (3, npix) I Q U in K_CMB.

    Returns {"cmb", "foreground", "total" = cmb + foreground} (each smoothed with the
    Gaussian beam of ``channel.fwhm_arcmin``, band limited at ``lmax``, no pixel window)
    and "foreground_source" (the flag of :func:`foreground_source`). The foreground is
    integrated over ``radiometry.channel_bandpass(channel)``; the CMB is realisation
    ``seed``, the same for every channel.
    """
    cmb = cmb_map(nside, lmax, r, master_seed, seed, channel.fwhm_arcmin)
    foreground = foreground_map(
        channel_bandpass(channel),
        nside,
        master_seed,
        channel.fwhm_arcmin,
        pysm_local_data,
        lmax=lmax,
        single_mode=single_mode,
    )
    return {
        "cmb": cmb,
        "foreground": foreground,
        "total": cmb + foreground,
        "foreground_source": foreground_source(pysm_local_data),
    }
