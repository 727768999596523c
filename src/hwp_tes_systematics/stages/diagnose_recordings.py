"""Stage: diagnose recordings against their simulation, and make an example recording.

The example is a recording of ``diagnose.example_channel`` whose nonlinearity comes
from the electrothermal TES model of the ``tes`` section (not from a polynomial), with
its own noise realization: the workflow checks its own diagnosis on it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from .. import config as cfg
from .. import sky
from ..diagnose import diagnose
from ..diagnose.recording import read_recording, write_recording
from ..diagnose.report.diagnosis import ReportPaths
from ..diagnose.simulate import simulate_recording
from ..instrument.channels import check_channel_name
from ..io import reuse_freed_memory, use_base_pages
from ..simulation.channel_inputs import (
    channel_a2_k_cmb,
    channel_conversion,
    channel_sky,
    tes_for_channel,
)

log = logging.getLogger(__name__)

EXAMPLE_NOISE_SEED = 1_000_003  # a noise realization no other job uses


def make_example(config: dict, out_h5: str, out_sky: str) -> None:
    """Simulate the example recording (electrothermal TES nonlinearity) and its sky map."""
    settings = config["diagnose"]
    name = settings["example_channel"]
    channel = cfg.channel(config, name)
    conversion = channel_conversion(config, name)
    tes_parameters = tes_for_channel(config["tes"], conversion["p_nominal_w"])
    sky_map = channel_sky(config, channel, 0)
    sky.write_sky_map(
        out_sky,
        sky_map["total"],
        extra_header={"CHANNEL": name},
        foreground_source=sky_map["foreground_source"],
        fwhm_arcmin=channel.fwhm_arcmin,
        freq_ghz=channel.bandcenter_ghz,
    )
    effect = (
        "tes_electrothermal",
        {
            "p0_w": conversion["p_nominal_w"],
            "kelvin_per_watt": conversion["kelvin_per_watt"],
            "tes_parameters": tes_parameters,
        },
    )
    recording = simulate_recording(
        name,
        settings["example_hours"],
        config["master_seed"],
        EXAMPLE_NOISE_SEED,
        sky_map["total"],
        conversion["a2_k_cmb"],
        effects=[effect],
        start_time_tdb=config["simulation"]["mission_start_tdb"],
    )
    write_recording(out_h5, recording)
    log.info(
        "%s: example recording (%.1f h, electrothermal TES) -> %s",
        name,
        settings["example_hours"],
        out_h5,
    )


def run(config: dict, recording_h5: str, sky_fits: str, out_json: str, out_md: str) -> None:
    """Diagnose one recording; writes ``out_json``, ``out_md`` and the figures beside it."""
    reuse_freed_memory()  # the fits' spectra of a row each: no page faults (io.reuse_freed_memory)
    use_base_pages()  # the first touch without compaction stalls (io.use_base_pages)
    recording = read_recording(recording_h5)
    # channel_a2_k_cmb gives 0 for a name outside the systematics channels: a name the
    # instrument model does not know is an error here, not an ideal HWP
    check_channel_name(
        recording.channel,
        f"{recording_h5}: the detectors' 'channel'",
        config["instrument"]["imo_location"],
    )
    a2_k = channel_a2_k_cmb(config, recording.channel)
    result = diagnose(
        recording,
        sky_fits,
        a2_k,
        out_dir=ReportPaths(Path(out_json), Path(out_md)),
        delta_bic_threshold=config["diagnose"]["delta_bic_threshold"],
    )
    with open(out_json) as handle:  # written by diagnose(); check it is complete JSON
        json.load(handle)
    names = [effect["name"] for effect in result["effects"]]
    log.info(
        "%s: mismatch %s %s; chi2 %.1f -> %.1f",
        recording_h5,
        result["mismatch_found"],
        names,
        result["chi2_before"],
        result["chi2_after"],
    )
