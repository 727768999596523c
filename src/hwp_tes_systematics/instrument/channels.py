"""LiteBIRD channels and detectors from the public PTEP instrument model.

The PTEP instrument model (IMo, release ``vPTEP``) ships inside litebird_sim as a
flat file (``lbs.PTEP_IMO_LOCATION``), so reading it needs no network. This module
turns it into small, frozen :class:`Channel` records holding what the study needs:
band, noise, beam, sampling, the telescope's HWP rotation rate, and the channel's
orthogonal detector pairs (one by default, as in the paper; N spread over the field of
view by :mod:`focal_plane`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .focal_plane import PixelPosition, choose_pixels, lay_out_pixels

TELESCOPES = ("LFT", "MFT", "HFT")
PAIR_SEARCH_DETECTORS = 16  # detectors searched for the default pair (8 pixels)
MAX_PAIR_NON_ORTHOGONALITY_DEG = 5.0  # a user-given pair must be this close to 90 deg


@dataclass(frozen=True)
class Channel:
    """One LiteBIRD frequency channel, as given by the PTEP instrument model."""

    name: str
    telescope: str
    bandcenter_ghz: float
    bandwidth_ghz: float
    band_freqs_ghz: np.ndarray
    band_weights: np.ndarray
    net_detector_ukrts: float
    fknee_mhz: float
    fmin_hz: float
    alpha: float
    fwhm_arcmin: float
    sampling_rate_hz: float
    hwp_rpm: float
    number_of_detectors: int
    detectors: tuple[str, ...]  # the simulated detectors, pair by pair (T, B, T, B, ...)
    # each detector's direction in the focal plane; None: all at the boresight (PTEP model)
    detector_positions: tuple[PixelPosition, ...] | None = None

    @property
    def n_pairs(self) -> int:
        return len(self.detectors) // 2

    @property
    def hwp_frequency_hz(self) -> float:
        """f_HWP = rpm / 60."""
        return self.hwp_rpm / 60.0


class InstrumentModelError(ValueError):
    """Raised when the instrument model lacks a requested channel or detector."""


@lru_cache(maxsize=4)
def open_imo(imo_location: str | None = None):
    """Open the instrument model; ``None`` means the PTEP flat file inside litebird_sim."""
    import litebird_sim as lbs

    location = lbs.PTEP_IMO_LOCATION if imo_location is None else imo_location
    if not Path(location).exists():
        raise InstrumentModelError(
            f"instrument.imo_location = {location!r}: no such file or directory "
            "(expected a litebird_sim IMo flat-file folder or schema.json[.gz])"
        )
    return lbs.Imo(flatfile_location=location)


def ptep_imo_location() -> Path:
    """litebird_sim's PTEP flat file (``lbs.PTEP_IMO_LOCATION``), found without importing
    litebird_sim (a few seconds, paid by every Snakemake job that only checks names)."""
    import importlib.util

    spec = importlib.util.find_spec("litebird_sim")
    if spec is None or not spec.submodule_search_locations:
        raise InstrumentModelError("litebird_sim is not installed: no PTEP instrument model")
    return Path(spec.submodule_search_locations[0]) / "default_imo" / "schema.json.gz"


@lru_cache(maxsize=4)
def channel_names_by_telescope(
    imo_location: str | None = None, release: str = "vPTEP"
) -> dict[str, list[str]]:
    """Channel names of each telescope in instrument-model order: the ``channel_names``
    of each telescope's ``instrument_info`` (what ``lbs.InstrumentInfo.from_imo`` reads),
    through libinsdb, the instrument database litebird_sim's ``Imo`` wraps."""
    from libinsdb import LocalInsDb

    location = ptep_imo_location() if imo_location is None else imo_location
    if not Path(location).exists():
        raise InstrumentModelError(
            f"instrument.imo_location = {str(location)!r}: no such file or directory "
            "(expected a litebird_sim IMo flat-file folder or schema.json[.gz])"
        )
    database = LocalInsDb(storage_path=str(location))
    names = {}
    for telescope in TELESCOPES:
        info = database.query(f"/releases/{release}/satellite/{telescope}/instrument_info")
        names[telescope] = list(info.metadata.get("channel_names", []))
    return names


def all_channel_names(imo_location: str | None = None, release: str = "vPTEP") -> list[str]:
    """All channel names (22 for vPTEP), LFT then MFT then HFT."""
    by_telescope = channel_names_by_telescope(imo_location, release)
    return [name for telescope in TELESCOPES for name in by_telescope[telescope]]


def telescope_of(channel_name: str, imo_location: str | None = None, release: str = "vPTEP") -> str:
    """The telescope (LFT, MFT, HFT) that holds ``channel_name``."""
    for telescope, names in channel_names_by_telescope(imo_location, release).items():
        if channel_name in names:
            return telescope
    raise InstrumentModelError(
        f"channel {channel_name!r} is not in instrument model release {release!r}"
        f"{_case_hint(channel_name, all_channel_names(imo_location, release))}; "
        f"expected one of {all_channel_names(imo_location, release)}"
    )


def _case_hint(name, known: list[str]) -> str:
    """' (did you mean 'M1-140'? names are case-sensitive)' for a name known in another case."""
    same = [k for k in known if isinstance(name, str) and k.lower() == name.lower()]
    return f" (did you mean {same[0]!r}? names are case-sensitive)" if same else ""


def check_channel_name(name, what: str, imo_location: str | None = None) -> str:
    """``name`` if it is a channel of the instrument model, else an
    :class:`InstrumentModelError` naming ``what`` (where the name came from), the value
    and the valid names."""
    known = all_channel_names(imo_location)
    if name not in known:
        raise InstrumentModelError(
            f"{what}: unknown channel {name!r}{_case_hint(name, known)}; expected one of "
            f"the PTEP instrument model's channels: {known}"
        )
    return name


@lru_cache(maxsize=64)
def channel_detector_names(
    channel_name: str, imo_location: str | None = None, release: str = "vPTEP"
) -> tuple[str, ...]:
    """The detector names of one channel, in instrument-model order."""
    import litebird_sim as lbs

    telescope = telescope_of(channel_name, imo_location, release)
    info = lbs.FreqChannelInfo.from_imo(
        open_imo(imo_location),
        f"/releases/{release}/satellite/{telescope}/{channel_name}/channel_info",
    )
    return tuple(info.detector_names)


def check_detector_names(
    channel_name: str, names, key: str, imo_location: str | None = None, release: str = "vPTEP"
) -> None:
    """Raise a clear error if a detector is not in ``channel_name`` (names the key, the
    detectors and, the channel holding hundreds, the first valid names and how many)."""
    known = channel_detector_names(channel_name, imo_location, release)
    unknown = [name for name in names if name not in known]
    if unknown:
        hints = "".join(_case_hint(name, list(known)) for name in unknown)
        raise InstrumentModelError(
            f"config key {key}: detector(s) {unknown} not in channel {channel_name!r} of "
            f"release {release!r}{hints}; expected two of its {len(known)} detectors, e.g. "
            f'{list(known[:6])} (all: python -c "from hwp_tes_systematics.instrument.channels '
            f'import channel_detector_names; print(channel_detector_names({channel_name!r}))")'
        )


def pixel_of(detector_name: str) -> str:
    """Pixel id of a PTEP detector name: its first three fields (wafer, ..., pixel)."""
    return "_".join(detector_name.split("_")[:3])


def most_orthogonal_pair(detector_names: list[str], pol_angles_rad: list[float]) -> tuple[str, str]:
    """The two detectors of one pixel whose polarisation angles are closest to 90 deg apart.

    Ties go to the earlier pair in model order.
    """
    best_pair, best_error_rad = None, np.inf
    for i, angle_i in enumerate(pol_angles_rad):
        for j in range(i + 1, len(pol_angles_rad)):
            if pixel_of(detector_names[i]) != pixel_of(detector_names[j]):
                continue
            error_rad = abs(np.mod(pol_angles_rad[j] - angle_i, np.pi) - np.pi / 2)
            if error_rad < best_error_rad - 1e-12:
                best_pair, best_error_rad = (detector_names[i], detector_names[j]), error_rad
    if best_pair is None:
        raise InstrumentModelError("no two detectors of the same pixel among the candidates")
    return best_pair


@lru_cache(maxsize=64)
def load_channel(
    channel_name: str,
    imo_location: str | None = None,
    release: str = "vPTEP",
    detector_pair: tuple[str, str] | None = None,
    pairs: int | str = 1,
    field_of_view_deg: tuple[float, float] | None = None,
) -> Channel:
    """Read one channel, choosing its detector pairs.

    ``detector_pair=None`` takes the first orthogonal pair in model order; the
    detectors' polarisation angles are read from the model to check the pair.
    ``pairs`` (an int, or "all" for every pixel with an orthogonal pair): that many
    pairs, the first being the one-pair choice and the others chosen by
    :func:`focal_plane.choose_pixels` over the layout of :func:`focal_plane.lay_out_pixels`.
    ``field_of_view_deg``: the semi-axes of the field of view the pixels fill; with it each
    detector gets its pixel's position, without it (the PTEP model as shipped) all point at
    the boresight (the choice of pairs still spreads over the layout of a unit field).
    """
    import litebird_sim as lbs

    imo = open_imo(imo_location)
    telescope = telescope_of(channel_name, imo_location, release)
    base = f"/releases/{release}/satellite/{telescope}"
    instrument = lbs.InstrumentInfo.from_imo(imo, f"{base}/instrument_info")
    info = lbs.FreqChannelInfo.from_imo(imo, f"{base}/{channel_name}/channel_info")

    def detector_info(detector_name: str):
        try:
            return lbs.DetectorInfo.from_imo(
                imo, f"{base}/{channel_name}/{detector_name}/detector_info"
            )
        except Exception as error:  # the IMo raises KeyError or its own error types
            known = list(info.detector_names)
            raise InstrumentModelError(
                f"detector {detector_name!r} is not in channel {channel_name!r} "
                f"of release {release!r}{_case_hint(detector_name, known)}; expected two of "
                f"its {len(known)} detectors, e.g. {known[:6]} (all: "
                "instrument.channel_detector_names)"
            ) from error

    def pol_angle(detector_name: str) -> float:
        return float(detector_info(detector_name).pol_angle_rad)

    if detector_pair is None:
        # Detectors come in T/B pairs of the same pixel: search the first few pixels only.
        candidates = list(info.detector_names[:PAIR_SEARCH_DETECTORS])
        pair = most_orthogonal_pair(candidates, [pol_angle(name) for name in candidates])
    else:
        pair = tuple(detector_pair)
        angles = [pol_angle(name) for name in pair]
        error_deg = abs(np.degrees(np.mod(angles[1] - angles[0], np.pi)) - 90.0)
        if error_deg > MAX_PAIR_NON_ORTHOGONALITY_DEG:
            raise InstrumentModelError(
                f"instrument.detector_pairs[{channel_name!r}] = {list(pair)}: polarisation "
                f"angles {np.degrees(angles)} deg are {error_deg:.1f} deg from orthogonal "
                f"(expected within {MAX_PAIR_NON_ORTHOGONALITY_DEG} deg)"
            )
    detectors, positions = pair, None
    if pairs != 1 or field_of_view_deg is not None:
        infos = [detector_info(name) for name in info.detector_names]
        pairs_of = pixel_pairs(infos)
        pixels = list(pairs_of)
        wafers = [next(d.wafer for d in infos if pixel_of(d.name) == p) for p in pixels]
        layout = lay_out_pixels(pixels, wafers, field_of_view_deg or (1.0, 1.0))
        n = len(pixels) if pairs == "all" else int(pairs)
        if not 1 <= n <= len(pixels):
            raise InstrumentModelError(
                f"instrument.pairs_per_channel = {pairs!r} for {channel_name}: the channel "
                f"has {len(pixels)} pixels with an orthogonal pair (expected 1..{len(pixels)} "
                "or 'all')"
            )
        pairs_of[pixel_of(pair[0])] = pair
        chosen = choose_pixels(layout, pixel_of(pair[0]), n)
        detectors = tuple(name for pixel in chosen for name in pairs_of[pixel])
        if field_of_view_deg is not None:
            positions = tuple(layout[pixel_of(name)] for name in detectors)

    return Channel(
        name=channel_name,
        telescope=telescope,
        bandcenter_ghz=float(info.bandcenter_ghz),
        bandwidth_ghz=float(info.bandwidth_ghz),
        band_freqs_ghz=np.asarray(info.band_freqs_ghz, dtype=float),
        band_weights=np.asarray(info.band_weights, dtype=float),
        net_detector_ukrts=float(info.net_detector_ukrts),
        fknee_mhz=float(info.fknee_mhz),
        fmin_hz=float(info.fmin_hz),
        alpha=float(info.alpha),
        fwhm_arcmin=float(info.fwhm_arcmin),
        sampling_rate_hz=float(info.sampling_rate_hz),
        hwp_rpm=float(instrument.hwp_rpm),
        number_of_detectors=int(info.number_of_detectors),
        detectors=tuple(detectors),
        detector_positions=positions,
    )


@lru_cache(maxsize=64)
def pixels_with_a_pair(
    channel_name: str, imo_location: str | None = None, release: str = "vPTEP"
) -> int:
    """How many pixels of a channel hold an orthogonal pair (PTEP: 12 to 244): the most
    pairs ``load_channel`` can simulate, ``pairs="all"``."""
    return load_channel(channel_name, imo_location, release, pairs="all").n_pairs


def pixel_pairs(detector_infos) -> dict[str, tuple[str, str]]:
    """{pixel: its most orthogonal pair} for every pixel holding two detectors, in model
    order (``detector_infos``: litebird_sim DetectorInfo of a channel)."""
    by_pixel: dict[str, list] = {}
    for detector in detector_infos:
        by_pixel.setdefault(pixel_of(detector.name), []).append(detector)
    return {
        pixel: most_orthogonal_pair([d.name for d in group], [d.pol_angle_rad for d in group])
        for pixel, group in by_pixel.items()
        if len(group) >= 2
    }


def check_channel_names(names: list[str], key: str, imo_location: str | None = None) -> None:
    """Raise a clear error if a configured channel name is not in the instrument model."""
    known = all_channel_names(imo_location)
    unknown = [name for name in names if name not in known]
    if unknown:
        hints = "".join(_case_hint(name, known) for name in unknown)
        raise InstrumentModelError(
            f"config key {key}: unknown channel(s) {unknown}{hints}; expected names from the "
            f"PTEP instrument model: {known}"
        )
