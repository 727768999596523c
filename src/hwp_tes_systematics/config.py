"""Configuration: JSON-schema validation with clear messages, and typed accessors.

The schema (``data/config.schema.yaml``) describes every key with its unit and
source and forbids unknown keys. Semantic checks that a schema cannot express
(channel names exist in the instrument model, curve files exist) follow.

The embedded default configuration ships with the package (``default_config_path``):
``data/config/`` holds symlinks to the repository's ``config/config.yaml`` and
``config/hwp/*.csv``, which an installed package (wheel) holds as copies. A relative
path written in a configuration file is found by ``resolve_path``: in the current
folder if it exists there (the workflow runs from the repository's top folder), else
under ``data/`` (so ``config/hwp/mft_hwp_curves.csv`` resolves from any folder once
the package is installed).
"""

from __future__ import annotations

import copy
from importlib import resources
from pathlib import Path

import jsonschema
import yaml

from . import instrument
from .instrument.hwp_power import HwpCurves, OpticalElement, read_hwp_curves

SCHEMA_RESOURCE = "config.schema.yaml"
DEFAULT_CONFIG_RESOURCE = "config/config.yaml"  # under data/, as in the repository
ONE_YEAR_REQUIREMENT_RESOURCE = "one_year_requirement.json"
# the run the shipped one-year requirement is (the repository's copy of it)
ONE_YEAR_REQUIREMENT_SOURCE = "docs/one_year/recovered_power/requirement.json"


class ConfigError(ValueError):
    """The configuration is invalid; the message names the key and what was expected."""


def data_path() -> Path:
    """Folder of the data shipped with the package: schema, default config, HWP curve tables."""
    return Path(str(resources.files("hwp_tes_systematics") / "data"))


def schema_path() -> Path:
    """Path of the configuration JSON schema shipped with the package."""
    return data_path() / SCHEMA_RESOURCE


def one_year_requirement_path() -> Path:
    """The shipped one-year answer (``docs/one_year/recovered_power/requirement.json``,
    packaged as ``data/one_year_requirement.json``): what ``diagnose`` compares a fitted
    g1 with, and what a shorter run is put beside."""
    return data_path() / ONE_YEAR_REQUIREMENT_RESOURCE


def default_config_path() -> Path:
    """Path of the embedded default configuration shipped with the package.

    In the repository it is a symlink to ``config/config.yaml`` (the file the Snakefile
    reads and users edit); an installed package holds a copy of it.
    """
    return data_path() / DEFAULT_CONFIG_RESOURCE


def resolve_path(path: str | Path) -> Path:
    """The file that a path written in a configuration names.

    An absolute path is used as it is. A relative path is looked up in the current
    folder first and, if it is not there, under the package's data folder, which ships
    ``config/config.yaml`` and ``config/hwp/*.csv`` under the same relative paths as the
    repository. A path found in neither place is returned as written, so that the
    reader's error names it as the user wrote it.
    """
    path = Path(path)
    if path.is_absolute() or path.exists():
        return path
    shipped = data_path() / path
    return shipped if shipped.exists() else path


def load_schema() -> dict:
    with open(schema_path()) as handle:
        return yaml.safe_load(handle)


def _key_path(error: jsonschema.ValidationError) -> str:
    return ".".join(str(part) for part in error.absolute_path) or "<top level>"


def validate_config(config: dict, source: str = "configuration") -> None:
    """Validate against the schema; raise ConfigError naming the offending key."""
    validator = jsonschema.Draft202012Validator(load_schema())
    errors = sorted(validator.iter_errors(config), key=lambda e: list(e.absolute_path))
    if not errors:
        return
    messages = []
    for error in errors[:10]:
        key = _key_path(error)
        if error.validator == "additionalProperties":
            messages.append(f"{key}: {error.message} (mistyped or unknown key?)")
        else:
            messages.append(f"{key} = {error.instance!r}: {error.message}")
    raise ConfigError(f"{source} is invalid:\n  " + "\n  ".join(messages))


def deep_merge(base: dict, override: dict) -> dict:
    """Recursively update a copy of ``base`` with ``override`` (as Snakemake's --configfile)."""
    merged = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


class _UniqueKeyLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the
    last silently: a setting edited in one place and read from another)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path) -> dict:
    """One YAML configuration file as a dict ({} if empty); ConfigError naming the file
    if it is not valid YAML or gives a key twice."""
    with open(path) as handle:
        try:
            return yaml.load(handle, Loader=_UniqueKeyLoader) or {}
        except yaml.YAMLError as error:
            raise ConfigError(f"configuration file {path}: not valid YAML ({error})") from error


def load_config(*paths: str | Path) -> dict:
    """Read YAML files, merge them in order, validate and check the result."""
    config: dict = {}
    for path in paths:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"configuration file {path}: not found")
        config = deep_merge(config, read_yaml(path))
    check_config(config, source=" + ".join(str(p) for p in paths))
    return config


def check_config(config: dict, source: str = "configuration") -> None:
    """Schema validation plus semantic checks (channels exist, curve files readable)."""
    validate_config(config, source)
    imo_location = config["instrument"]["imo_location"]
    try:
        channels = selected_channels(config)
        instrument.check_channel_names(
            config["instrument"]["systematics_channels"],
            "instrument.systematics_channels",
            imo_location,
        )
        instrument.check_channel_names(
            list(config["instrument"]["detector_pairs"]), "instrument.detector_pairs", imo_location
        )
        for name, pair in config["instrument"]["detector_pairs"].items():
            instrument.check_detector_names(
                name, list(pair), f"instrument.detector_pairs[{name!r}]", imo_location
            )
        instrument.check_channel_names([config["tes"]["figure_channel"]], "tes.figure_channel")
        instrument.check_channel_names(
            [config["figures"]["tod_channel"]], "figures.tod_channel", imo_location
        )
        instrument.check_channel_names(
            [config["diagnose"]["example_channel"]], "diagnose.example_channel", imo_location
        )
    except instrument.InstrumentModelError as error:
        raise ConfigError(f"{source}: {error}") from error
    outside = [c for c in config["instrument"]["systematics_channels"] if c not in channels]
    if outside:
        raise ConfigError(
            f"{source}: instrument.systematics_channels {outside} are not among "
            f"instrument.channels {channels}"
        )
    _check_fixed_pass_variants(config, source)
    _check_emulated_pairs(config, channels, source)
    nside = config["maps"]["nside"]
    if analysis_nside(config) > nside:
        raise ConfigError(
            f"{source}: component_separation.analysis_nside = {analysis_nside(config)} "
            f"exceeds maps.nside = {nside} (the mask's region is decided on a grid no finer "
            "than the maps')"
        )
    spectra_lmax = analysis_lmax(config)
    if config["likelihood"]["lmax"] > spectra_lmax:
        raise ConfigError(
            f"{source}: likelihood.lmax = {config['likelihood']['lmax']} exceeds the spectra's "
            f"lmax = {spectra_lmax} (component_separation.lmax, default 2 analysis_nside)"
        )
    if config["tes"]["tbath_k"] >= config["tes"]["tc_k"]:
        raise ConfigError(
            f"{source}: tes.tbath_k = {config['tes']['tbath_k']} must be below "
            f"tes.tc_k = {config['tes']['tc_k']} (a TES needs a bath colder than Tc)"
        )


def _check_emulated_pairs(config: dict, channels: list[str], source: str) -> None:
    """instrument.emulated_pairs_per_channel needs the map-domain seeds (the noise and the
    templates are scaled there), no template fit (a fit of N_e detectors' templates is not
    one of N scaled) and, per channel, at least the simulated pairs and at most the
    channel's own."""
    settings = config["instrument"]
    emulated = settings["emulated_pairs_per_channel"]
    if emulated is None:
        return
    key = f"{source}: instrument.emulated_pairs_per_channel = {emulated!r}"
    if config["simulation"]["realizations"] != "map_domain":
        raise ConfigError(
            f"{key} needs simulation.realizations: map_domain (the seeds are scaled in the "
            f"map domain), not {config['simulation']['realizations']!r}"
        )
    if config["mitigation"]["template_fit"] is not None:
        raise ConfigError(
            f"{key} needs mitigation.template_fit: null (a fit of the emulated detectors' "
            "templates is not the fit of the simulated ones, scaled)"
        )
    for name in channels:
        simulated = _pair_count(config, name, settings["pairs_per_channel"])
        wanted = _pair_count(config, name, emulated)
        most = _pair_count(config, name, "all")
        if not simulated <= wanted <= most:
            raise ConfigError(
                f"{key} for {name}: expected from the simulated pairs "
                f"(instrument.pairs_per_channel, {simulated}) to the channel's {most}"
            )


def analysis_nside(config: dict) -> int:
    """The resolution the analysis mask's region is decided on
    (component_separation.analysis_nside, else maps.nside)."""
    return config["component_separation"].get("analysis_nside") or config["maps"]["nside"]


def analysis_lmax(config: dict) -> int:
    """The last multipole of the HILC and the spectra (component_separation.lmax, else
    2 analysis_nside)."""
    return config["component_separation"]["lmax"] or 2 * analysis_nside(config)


def fixed_pass_nsides(config: dict) -> list[int]:
    """The resolutions the fixed TOD pass bins (simulation.fixed_pass_nsides or maps.nside)."""
    return list(config["simulation"]["fixed_pass_nsides"] or [config["maps"]["nside"]])


def fixed_pass_baselines(config: dict) -> list[float | None]:
    """The baseline lengths [s] the fixed pass bins (None: no baselines)."""
    lengths = config["simulation"]["fixed_pass_baseline_lengths_s"]
    return list(lengths) if lengths is not None else [config["maps"]["baseline_length_s"]]


def scan_nside(config: dict) -> int:
    """The resolution of the sky a TOD scans: the highest the fixed pass bins."""
    return max(fixed_pass_nsides(config))


def map_variant(nside: int, baseline_length_s: float | None, demodulated: bool = False) -> str:
    """The name of one map-maker of the fixed pass, e.g. nside64_baselines60s, or
    nside64_nobaselines_demodulated for the HWP-demodulating one."""
    suffix = "_demodulated" if demodulated else ""
    if baseline_length_s is None:
        return f"nside{nside}_nobaselines{suffix}"
    return f"nside{nside}_baselines{baseline_length_s:g}s{suffix}"


def fixed_pass_variants(config: dict) -> list[tuple[int, float | None]]:
    """(nside, baseline length) of every map-maker of the fixed pass; the scan
    resolution's first baseline length first (the pass's primary binning)."""
    nsides = sorted(fixed_pass_nsides(config), reverse=True)
    return [(n, b) for n in nsides for b in fixed_pass_baselines(config)]


def demodulated_variants(config: dict) -> list[tuple[int, float | None]]:
    """(nside, baseline length) of every demodulating map-maker of the fixed pass: each of
    :func:`fixed_pass_variants` with simulation.fixed_pass_demodulated, else none."""
    return fixed_pass_variants(config) if config["simulation"]["fixed_pass_demodulated"] else []


def fixed_pass_variant_names(config: dict) -> list[str]:
    """The names of every map-maker of the fixed pass (one file each): the binned ones of
    :func:`fixed_pass_variants`, then the demodulating ones."""
    binned = [map_variant(*variant) for variant in fixed_pass_variants(config)]
    return binned + [map_variant(*v, demodulated=True) for v in demodulated_variants(config)]


def moments_variant(config: dict, nside: int) -> str:
    """The map-maker of a resolution whose fixed pass file holds that resolution's HWPSS
    moments (its first in :func:`fixed_pass_variants`; the others point to it)."""
    return map_variant(nside, next(b for n, b in fixed_pass_variants(config) if n == nside))


def analysis_variant(config: dict) -> str:
    """The fixed-pass map-maker the analysis reads: maps.nside, maps.baseline_length_s and
    maps.map_maker."""
    maps = config["maps"]
    return map_variant(maps["nside"], maps["baseline_length_s"], maps["map_maker"] == "demodulated")


def _check_fixed_pass_variants(config: dict, source: str) -> None:
    simulation, maps = config["simulation"], config["maps"]
    given = [k for k in ("fixed_pass_nsides", "fixed_pass_baseline_lengths_s") if simulation[k]]
    if given and simulation["realizations"] != "map_domain":
        raise ConfigError(
            f"{source}: simulation.{given[0]} bins several map-makers in the map-domain fixed "
            "pass; it needs simulation.realizations: map_domain"
        )
    if simulation["fixed_pass_demodulated"] and simulation["realizations"] != "map_domain":
        raise ConfigError(
            f"{source}: simulation.fixed_pass_demodulated bins a demodulating map-maker in the "
            "map-domain fixed pass; it needs simulation.realizations: map_domain"
        )
    if simulation["fixed_pass_demodulated"] and config["notch"]["width_divisor"] is None:
        raise ConfigError(
            f"{source}: simulation.fixed_pass_demodulated needs the notch (notch.width_divisor "
            "not null): the demodulation's low-pass uses its margins"
        )
    if maps["map_maker"] == "demodulated":
        missing = [
            f"simulation.{key}: {value}"
            for key, value, wanted in (
                ("realizations", simulation["realizations"], "map_domain"),
                ("fixed_pass_demodulated", simulation["fixed_pass_demodulated"], True),
                ("sky_scanning", simulation["sky_scanning"], "band_limited"),
            )
            if value != wanted
        ]
        if missing:
            raise ConfigError(
                f"{source}: maps.map_maker demodulated needs simulation.realizations "
                "map_domain, simulation.fixed_pass_demodulated true and "
                f"simulation.sky_scanning band_limited; got {', '.join(missing)}"
            )
    if maps["nside"] not in fixed_pass_nsides(config):
        raise ConfigError(
            f"{source}: maps.nside = {maps['nside']} is not among simulation.fixed_pass_nsides "
            f"{simulation['fixed_pass_nsides']} (the resolutions the fixed pass bins)"
        )
    if maps["baseline_length_s"] not in fixed_pass_baselines(config):
        raise ConfigError(
            f"{source}: maps.baseline_length_s = {maps['baseline_length_s']} is not among "
            f"simulation.fixed_pass_baseline_lengths_s "
            f"{simulation['fixed_pass_baseline_lengths_s']}"
        )


def selected_channels(config: dict) -> list[str]:
    """The simulated channels in instrument-model order ("all" -> the 22 PTEP channels)."""
    imo_location = config["instrument"]["imo_location"]
    every = instrument.all_channel_names(imo_location, config["instrument"]["imo_release"])
    chosen = config["instrument"]["channels"]
    if chosen == "all":
        return every
    instrument.check_channel_names(chosen, "instrument.channels", imo_location)
    return [name for name in every if name in chosen]


def channel(config: dict, name: str) -> instrument.Channel:
    """Channel record with the configured detector pairs and their positions."""
    settings = config["instrument"]
    pair = settings["detector_pairs"].get(name)
    field_of_view = None
    if settings["detector_positions"] == "field_of_view":
        telescope = instrument.telescope_of(name, settings["imo_location"], settings["imo_release"])
        field_of_view = tuple(settings["field_of_view_semi_axes_deg"][telescope])
    return instrument.load_channel(
        name,
        settings["imo_location"],
        settings["imo_release"],
        tuple(pair) if pair else None,
        settings["pairs_per_channel"],
        field_of_view,
    )


def _pair_count(config: dict, channel_name: str, pairs: int | str) -> int:
    """``pairs`` (a count, or "all") of a channel as a number of pairs."""
    if pairs != "all":
        return int(pairs)
    settings = config["instrument"]
    return instrument.pixels_with_a_pair(
        channel_name, settings["imo_location"], settings["imo_release"]
    )


def emulated_pairs_factor(config: dict, channel_name: str) -> float:
    """f = N / N_e: the channel's simulated pairs N (instrument.pairs_per_channel) over the
    pairs its map-domain seeds emulate, N_e (instrument.emulated_pairs_per_channel; f = 1
    when null). A seed of N_e pairs has the binned white noise of N pairs times sqrt(f)
    (M^-1 scales as 1 / N_e) and each detector's share of the map times f, with N_e / N
    times as many detectors: a random g1's template power, sum_k C_ell(T_k), scales as f,
    and so does a common g1's where distinct pixels' templates are uncorrelated
    (docs/physics/focal_plane.md). The seeds carry the first by the noise, the second by
    g1 draws times sqrt(f) (:func:`..analysis.channel_alms.channel_g1_draws`)."""
    settings = config["instrument"]
    emulated = settings["emulated_pairs_per_channel"]
    if emulated is None:
        return 1.0
    simulated = _pair_count(config, channel_name, settings["pairs_per_channel"])
    return simulated / _pair_count(config, channel_name, emulated)


def simulated_rate_hz(config: dict, channel) -> float:
    """The TOD sampling rate of ``channel`` [Hz]: simulation.sampling_rate_without_systematics_hz
    for a channel outside instrument.systematics_channels if set (its TOD holds nothing
    above 4 f_HWP + the sky band: no d^2 to 8 f_HWP), else simulation.sampling_rate_hz,
    else the instrument model's."""
    simulation = config["simulation"]
    rate = simulation["sampling_rate_hz"] or channel.sampling_rate_hz
    if channel.name in config["instrument"]["systematics_channels"]:
        return rate
    return simulation["sampling_rate_without_systematics_hz"] or rate


def noise_shaping_key(config: dict, channel_name: str) -> tuple:
    """What a channel's noise shaping S_ell, S^h_ell depends on besides the realizations
    drawn: the filter (its HWP frequency: the notch sits at 4 f_HWP), the sampling rate,
    the noise spectrum's shape (f_knee, f_min, alpha; not its level: S is a ratio) and
    whether h n is measured (systematics). The map-maker, the duration and the notch are
    the run's. Channels with equal keys (a telescope's, in the PTEP model) differ only by
    their focal-plane position: their S agree within the realizations' scatter
    (docs/physics/map_domain.md)."""
    channel_record = channel(config, channel_name)
    return (
        channel_record.hwp_rpm,
        simulated_rate_hz(config, channel_record),
        channel_record.fknee_mhz,
        channel_record.fmin_hz,
        channel_record.alpha,
        channel_name in config["instrument"]["systematics_channels"],
    )


def noise_shaping_siblings(config: dict, channel_name: str) -> list[str]:
    """The channels of the run whose measured noise shaping is pooled with
    ``channel_name``'s (itself included, in the run's order): those with its
    :func:`noise_shaping_key` when ``simulation.noise_shaping_pooling`` is "telescope",
    itself alone when it is "channel"."""
    if config["simulation"]["noise_shaping_pooling"] == "channel":
        return [channel_name]
    key = noise_shaping_key(config, channel_name)
    return [
        name
        for name in selected_channels(config)
        if name == channel_name or noise_shaping_key(config, name) == key
    ]


def telescope_optics(config: dict, telescope: str) -> tuple[HwpCurves, list[OpticalElement], float]:
    """(HWP curves, elements after the HWP, HWP temperature [K]) of one telescope."""
    optics = config["optics"]["telescopes"][telescope]
    curves_path = optics["hwp_curves_csv"]
    curves = (
        HwpCurves.ideal() if curves_path is None else read_hwp_curves(resolve_path(curves_path))
    )
    elements = [OpticalElement(**element) for element in optics["elements_after_hwp"]]
    return curves, elements, float(optics["hwp_temperature_k"])


def config_reference_markdown() -> str:
    """The configuration reference (every key, type, description) as Markdown, from the schema."""
    schema = load_schema()
    definitions = schema.get("$defs", {})
    lines = [
        "# Configuration reference",
        "",
        "Generated from `src/hwp_tes_systematics/data/config.schema.yaml` by",
        "`python -m hwp_tes_systematics config-reference > docs/config_reference.md`",
        "(a test keeps the two in step). Unknown keys are errors.",
        "",
        "| key | type | description (unit; source) |",
        "|---|---|---|",
    ]

    def resolve(node: dict) -> dict:
        if "$ref" in node:
            target = definitions[node["$ref"].split("/")[-1]]
            return {**target, **{k: v for k, v in node.items() if k != "$ref"}}
        return node

    def type_of(node: dict) -> str:
        if "oneOf" in node:
            return " or ".join(type_of(resolve(option)) for option in node["oneOf"])
        if "const" in node:
            return f"`{node['const']}`"
        kind = node.get("type", "")
        return "/".join(kind) if isinstance(kind, list) else kind

    def walk(node: dict, prefix: str) -> None:
        for key, child in node.get("properties", {}).items():
            child = resolve(child)
            name = f"{prefix}{key}"
            description = " ".join(child.get("description", "").split())
            lines.append(f"| `{name}` | {type_of(child)} | {description} |")
            walk(child, f"{name}.")
            items = child.get("items")
            if isinstance(items, dict):
                walk(resolve(items), f"{name}[].")

    walk(schema, "")
    return "\n".join(lines) + "\n"
