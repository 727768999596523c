"""Stage: beam-smoothed, band-integrated foreground maps of every channel (FITS, K_CMB).

The foregrounds do not change between realizations, so they are made once, in one
process (pysm3 compiles its kernels once), and read by every (channel, seed) job.
"""

from __future__ import annotations

import logging

from .. import config as cfg
from .. import sky
from ..instrument.radiometry import channel_bandpass

log = logging.getLogger(__name__)


def run(config: dict, channel_names: list[str], out_paths: list[str]) -> None:
    nside = cfg.scan_nside(config)  # the resolution the TODs scan
    local_data = config["simulation"]["pysm_local_data"]
    source = sky.foreground_source(local_data)
    for name, path in zip(channel_names, out_paths, strict=True):
        channel = cfg.channel(config, name)
        foreground = sky.foreground_map(
            channel_bandpass(channel),
            nside,
            config["master_seed"],
            channel.fwhm_arcmin,
            local_data,
            lmax=3 * nside - 1,
        )
        sky.write_sky_map(
            path,
            foreground,
            extra_header={"CHANNEL": name},
            foreground_source=source,
            fwhm_arcmin=channel.fwhm_arcmin,
            freq_ghz=channel.bandcenter_ghz,
        )
        log.info("%s: foreground map (%s) -> %s", name, source, path)
