"""The instrument and its inputs: LiteBIRD channels and detectors (PTEP model), the HWP's
optical power and A_2, band-integrated radiometry (K/W), the TES response and its
nonlinearity (the physics; a channel's inputs computed from the configuration are in
:mod:`..simulation.channel_inputs`).

The channel model (:mod:`.channels`) is re-exported here: ``from hwp_tes_systematics.instrument
import load_channel``.
"""

from .channels import (
    MAX_PAIR_NON_ORTHOGONALITY_DEG,
    PAIR_SEARCH_DETECTORS,
    TELESCOPES,
    Channel,
    InstrumentModelError,
    all_channel_names,
    channel_detector_names,
    channel_names_by_telescope,
    check_channel_name,
    check_channel_names,
    check_detector_names,
    load_channel,
    most_orthogonal_pair,
    open_imo,
    pixel_of,
    pixels_with_a_pair,
    telescope_of,
)

__all__ = [
    "MAX_PAIR_NON_ORTHOGONALITY_DEG",
    "PAIR_SEARCH_DETECTORS",
    "TELESCOPES",
    "Channel",
    "InstrumentModelError",
    "all_channel_names",
    "channel_detector_names",
    "channel_names_by_telescope",
    "check_channel_name",
    "check_channel_names",
    "check_detector_names",
    "load_channel",
    "most_orthogonal_pair",
    "open_imo",
    "pixel_of",
    "pixels_with_a_pair",
    "telescope_of",
]
