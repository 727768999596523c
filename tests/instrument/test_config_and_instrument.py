"""Configuration validation and the PTEP instrument model."""

import copy

import numpy as np
import pytest
import yaml

from hwp_tes_systematics import instrument
from hwp_tes_systematics.config import (
    ConfigError,
    check_config,
    load_config,
    load_schema,
    read_yaml,
    selected_channels,
)


def test_all_22_ptep_channels_with_telescope_hwp_rates():
    names = instrument.all_channel_names()
    assert len(names) == 22
    rpm = {"LFT": 46.0, "MFT": 39.0, "HFT": 61.0}
    for name in ("L1-040", "M1-140", "H3-402"):
        channel = instrument.load_channel(name)
        assert channel.hwp_rpm == rpm[channel.telescope]
        assert channel.sampling_rate_hz == 31.0
        a, b = channel.detectors
        assert instrument.pixel_of(a) == instrument.pixel_of(b)
    assert instrument.load_channel("M1-140").hwp_frequency_hz == pytest.approx(0.65)


def test_default_config_is_valid_and_selects_everything(default_config):
    assert len(selected_channels(default_config)) == 22
    assert len(default_config["instrument"]["systematics_channels"]) == 10


def test_every_schema_key_has_a_description():
    """Every leaf property of the schema is described (unit and source live there)."""

    def walk(node, path):
        if isinstance(node, dict):
            for key, value in node.get("properties", {}).items():
                assert "description" in value, f"{path}.{key} has no description"
                walk(value, f"{path}.{key}")
            for value in node.get("$defs", {}).values():
                walk(value, path)

    walk(load_schema(), "config")


def _emulated(config, emulated, **changes):
    config["instrument"]["emulated_pairs_per_channel"] = emulated
    config["mitigation"]["template_fit"] = None
    for key, value in changes.items():
        section, name = key.split("__")
        config[section][name] = value


@pytest.mark.parametrize(
    "mutate, message",
    [
        (
            lambda c: _emulated(c, 4, simulation__realizations="tod"),
            "emulated_pairs_per_channel = 4 needs simulation.realizations: map_domain",
        ),
        (
            lambda c: _emulated(c, 4, mitigation__template_fit="detector"),
            "needs mitigation.template_fit: null",
        ),
        (
            lambda c: _emulated(c, 2, instrument__pairs_per_channel=4),
            "= 2 for L1-040: expected from the simulated pairs (instrument.pairs_per_channel, 4)",
        ),
        (lambda c: _emulated(c, 13), "= 13 for L2-050: expected from the simulated pairs"),
    ],
)
def test_an_emulated_focal_plane_needs_map_domain_seeds_and_a_count_in_range(
    default_config, mutate, message
):
    config = copy.deepcopy(default_config)
    mutate(config)
    with pytest.raises(ConfigError) as error:
        check_config(config)
    assert message in str(error.value)


def test_the_emulated_pairs_factor_is_simulated_over_emulated_pairs(default_config):
    """f = N / N_e per channel: every pair of the PTEP model ("all": 2,254 pairs, 12 to
    244 per channel) emulated from one or from eight; 1 when nothing is emulated."""
    from hwp_tes_systematics.config import emulated_pairs_factor

    config = copy.deepcopy(default_config)
    assert emulated_pairs_factor(config, "M2-119") == 1.0
    _emulated(config, "all")
    check_config(config)
    counts = {
        name: round(1 / emulated_pairs_factor(config, name)) for name in selected_channels(config)
    }
    assert sum(counts.values()) == 2254  # 4,508 detectors
    assert (counts["L2-050"], counts["M2-119"], counts["H3-402"]) == (12, 244, 169)
    config["instrument"]["pairs_per_channel"] = 8
    assert emulated_pairs_factor(config, "M2-119") == pytest.approx(8 / 244)
    config["instrument"]["emulated_pairs_per_channel"] = 12
    assert emulated_pairs_factor(config, "L2-050") == pytest.approx(8 / 12)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: c["tes"].__setitem__("tc_kelvin", 0.17), "tc_kelvin"),
        (
            lambda c: c["optics"]["telescopes"]["MFT"].__setitem__("hwp_temperature_k", -20.0),
            "optics.telescopes.MFT.hwp_temperature_k = -20.0",
        ),
        (lambda c: c["instrument"].__setitem__("systematics_channels", ["M9-999"]), "M9-999"),
        (
            lambda c: c["figures"].__setitem__("tod_channel", "m1-140"),
            "figures.tod_channel: unknown channel(s) ['m1-140'] (did you mean 'M1-140'?",
        ),
        (
            lambda c: c["instrument"]["detector_pairs"].__setitem__(
                "M1-140", ["001_002_030_00A_140_T", "001_002_030_00a_140_B"]
            ),
            "instrument.detector_pairs['M1-140']: detector(s) ['001_002_030_00a_140_B']",
        ),
        (lambda c: c["tes"].__setitem__("tbath_k", 0.2), "tes.tbath_k"),
        (lambda c: c.__setitem__("master_seed", "abc"), "master_seed"),
        (
            lambda c: c["component_separation"].__setitem__("analysis_nside", 128),
            "component_separation.analysis_nside = 128 exceeds maps.nside = 64",
        ),
        (
            lambda c: c["component_separation"].__setitem__("analysis_nside", 48),
            "component_separation.analysis_nside = 48",
        ),
    ],
)
def test_bad_config_names_the_key(default_config, mutate, message):
    config = copy.deepcopy(default_config)
    mutate(config)
    with pytest.raises(ConfigError) as error:
        check_config(config)
    assert message in str(error.value)


@pytest.mark.parametrize("name", ["X9-999", "m1-140", "", None])
def test_unknown_channel_names_the_value_and_lists_the_valid_ones(name):
    """check_channel_name (the API and the diagnosis stage use it): an unknown or
    wrongly-cased channel is an error naming where it came from, the value, a case hint
    and all 22 valid names; a known one is returned."""
    with pytest.raises(instrument.InstrumentModelError) as error:
        instrument.check_channel_name(name, "recording.h5: the detectors' 'channel'")
    message = str(error.value)
    assert message.startswith(f"recording.h5: the detectors' 'channel': unknown channel {name!r}")
    assert all(valid in message for valid in instrument.all_channel_names())
    assert ("did you mean 'M1-140'?" in message) == (name == "m1-140")
    assert instrument.check_channel_name("M1-140", "x") == "M1-140"


def test_user_config_merges_over_default(tmp_path, repo, monkeypatch):
    monkeypatch.chdir(repo)
    override = tmp_path / "user.yaml"
    override.write_text(
        yaml.safe_dump(
            {"instrument": {"channels": ["M1-140", "L1-040"], "systematics_channels": ["M1-140"]}}
        )
    )
    config = load_config(repo / "config/config.yaml", override)
    assert selected_channels(config) == ["L1-040", "M1-140"]  # instrument-model order
    assert config["tes"]["tc_k"] == 0.171  # untouched keys keep their defaults


def test_systematics_channels_must_be_simulated(tmp_path, repo, monkeypatch):
    monkeypatch.chdir(repo)
    override = tmp_path / "user.yaml"
    override.write_text(yaml.safe_dump({"instrument": {"channels": ["L1-040"]}}))
    with pytest.raises(ConfigError, match="not among instrument.channels"):
        load_config(repo / "config/config.yaml", override)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")


def test_a_key_given_twice_is_refused_and_no_shipped_file_has_one(tmp_path, repo):
    """PyYAML keeps the last of two equal keys silently; the configuration reader names
    the key and the file. Every shipped YAML configuration is read with it."""
    twice = tmp_path / "twice.yaml"
    twice.write_text("simulation:\n  seeds: 2\n  seeds: 3\n")
    with pytest.raises(ConfigError, match=r"twice.yaml.*'seeds' given twice"):
        load_config(repo / "config/config.yaml", twice)
    shipped = [*(repo / "config").glob("*.yaml"), *(repo / "tests/configs").glob("*.yaml")]
    assert len(shipped) > 5
    for path in shipped:
        read_yaml(path)


def test_unknown_detector_of_a_pair_is_named_with_valid_ones():
    """load_channel (the API) with a detector the channel lacks, or in the wrong case."""
    with pytest.raises(instrument.InstrumentModelError) as error:
        instrument.load_channel(
            "L1-040", detector_pair=("000_000_006_UA_040_T", "000_000_006_ua_040_B")
        )
    message = str(error.value)
    assert "detector '000_000_006_ua_040_B' is not in channel 'L1-040'" in message
    assert "did you mean '000_000_006_UA_040_B'?" in message
    assert "expected two of its" in message and "000_000_003_QA_040_T" in message


def test_user_detector_pair_must_be_orthogonal():
    with pytest.raises(instrument.InstrumentModelError, match="not orthogonal|from orthogonal"):
        instrument.load_channel(
            "L1-040", detector_pair=("000_000_003_QA_040_T", "000_000_005_UA_040_T")
        )
    channel = instrument.load_channel(
        "L1-040", detector_pair=("000_000_006_UA_040_T", "000_000_006_UA_040_B")
    )
    assert channel.detectors[0].endswith("_T")
    assert np.isfinite(channel.fwhm_arcmin)


def test_config_reference_in_docs_is_in_step_with_schema(repo):
    from hwp_tes_systematics.config import config_reference_markdown

    assert (repo / "docs/config_reference.md").read_text() == config_reference_markdown(), (
        "regenerate: python -m hwp_tes_systematics config-reference > docs/config_reference.md"
    )


@pytest.mark.parametrize("name", ["paper.yaml", "one_year.yaml"])
def test_shipped_configurations_merge_over_the_default(repo, monkeypatch, name):
    """The configurations the README names validate when merged over the default."""
    monkeypatch.chdir(repo)
    config = load_config(repo / "config/config.yaml", repo / "config" / name)
    assert config["simulation"]["duration_days"] == 365.25


@pytest.mark.parametrize(
    ("overlay", "baseline_length_s"),
    [("config/no_baselines.yaml", None), ("config/one_day_offsets.yaml", 86400.0)],
)
def test_offset_overlays_merge_after_one_year(repo, monkeypatch, overlay, baseline_length_s):
    """config/no_baselines.yaml and config/one_day_offsets.yaml, given after one_year.yaml,
    change only the offsets' removal (none; one per detector per day, i.e. per chunk)."""
    monkeypatch.chdir(repo)
    base = load_config(repo / "config/config.yaml", repo / "config/one_year.yaml")
    overlaid = load_config(
        repo / "config/config.yaml", repo / "config/one_year.yaml", repo / overlay
    )
    assert base["maps"]["baseline_length_s"] == 60.0
    assert overlaid["maps"]["baseline_length_s"] == baseline_length_s
    if baseline_length_s is not None:  # one interval per chunk, none shorter
        assert baseline_length_s == overlaid["simulation"]["chunk_duration_s"]
    overlaid["maps"]["baseline_length_s"] = 60.0
    assert overlaid == base


def test_map_domain_validation_overlays_differ_only_in_the_path(repo, monkeypatch):
    """config/map_domain_validation.yaml puts one month at one year's per-pixel noise
    (noise_scale^2 = duration / one year); config/tod_path.yaml after it switches the path
    and nothing else."""
    monkeypatch.chdir(repo)
    files = ["config/config.yaml", "config/one_year.yaml", "config/map_domain_validation.yaml"]
    map_domain = load_config(*files)
    tod = load_config(*files, "config/tod_path.yaml")
    simulation = map_domain["simulation"]
    assert simulation["realizations"] == "map_domain"
    assert simulation["noise_scale"] ** 2 == pytest.approx(
        simulation["duration_days"] / 365.25, rel=1e-5
    )
    assert set(map_domain["instrument"]["systematics_channels"]) <= set(
        map_domain["instrument"]["channels"]
    )
    assert tod["simulation"].pop("realizations") == "tod"
    map_domain["simulation"].pop("realizations")
    assert tod == map_domain


def test_resolution_overlays_share_one_fixed_pass(repo, monkeypatch):
    """config/nside<N>.yaml after one_year.yaml and resolution_study.yaml (with or without
    no_baselines.yaml): each analyses its own map-maker of the same fixed pass, whose
    configuration they share;
    an analysis map-maker outside the pass, or the pass's lists on the TOD path, are
    errors naming the key."""
    from hwp_tes_systematics.config import (
        ConfigError,
        analysis_variant,
        deep_merge,
        fixed_pass_variants,
    )

    monkeypatch.chdir(repo)
    passes, variants = set(), set()
    for nside in (64, 128, 256, 512):
        for extra in ([], ["config/no_baselines.yaml"]):
            files = ["config/config.yaml", "config/one_year.yaml", "config/resolution_study.yaml"]
            files.append(f"config/nside{nside}.yaml")
            config = load_config(*files, *extra)
            passes.add(str(fixed_pass_variants(config)))
            variants.add(analysis_variant(config))
    assert len(passes) == 1 and len(variants) == 8
    assert fixed_pass_variants(config)[0] == (512, 60.0)  # the scan's resolution first
    config = load_config("config/config.yaml", "config/one_year.yaml", "config/nside512.yaml")
    assert fixed_pass_variants(config) == [(512, 60.0)]  # alone: its own pass
    config = load_config(
        "config/config.yaml",
        "config/one_year.yaml",
        "config/resolution_study.yaml",
        "config/nside128.yaml",
    )
    with pytest.raises(ConfigError, match="maps.nside = 32 is not among"):
        check_config(deep_merge(config, {"maps": {"nside": 32}}))
    with pytest.raises(ConfigError, match="maps.baseline_length_s = 30.0 is not among"):
        check_config(deep_merge(config, {"maps": {"baseline_length_s": 30.0}}))
    with pytest.raises(ConfigError, match="needs simulation.realizations: map_domain"):
        check_config(deep_merge(config, {"simulation": {"realizations": "tod"}}))


def test_both_map_makers_overlay_shares_one_pass_at_the_run_nside(repo, monkeypatch):
    """config/both_map_makers.yaml bins the run's own nside with 60 s baselines and
    without in one pass; no_baselines.yaml after it picks the second analysis."""
    from hwp_tes_systematics.config import analysis_variant, fixed_pass_variants

    monkeypatch.chdir(repo)
    files = ["config/config.yaml", "config/one_year.yaml", "config/both_map_makers.yaml"]
    with_baselines = load_config(*files)
    without = load_config(*files, "config/no_baselines.yaml")
    assert fixed_pass_variants(with_baselines) == [(64, 60.0), (64, None)]
    assert fixed_pass_variants(without) == fixed_pass_variants(with_baselines)
    assert analysis_variant(with_baselines) != analysis_variant(without)
    check_config(without)


def test_a_demodulated_analysis_reads_its_own_file_of_the_pass(repo, monkeypatch):
    """simulation.fixed_pass_demodulated adds a demodulating map-maker per binned one (its
    own file); maps.map_maker demodulated reads it, and is refused without the pass's
    demodulated map-makers or a band-limited sky scan (names the keys)."""
    from hwp_tes_systematics.config import (
        ConfigError,
        analysis_variant,
        deep_merge,
        fixed_pass_variant_names,
    )

    monkeypatch.chdir(repo)
    config = load_config("config/config.yaml", "config/one_year.yaml")
    demodulated = deep_merge(
        config,
        {
            "simulation": {"fixed_pass_demodulated": True, "sky_scanning": "band_limited"},
            "maps": {"map_maker": "demodulated"},
        },
    )
    check_config(demodulated)
    assert fixed_pass_variant_names(demodulated) == [
        "nside64_baselines60s",
        "nside64_baselines60s_demodulated",
    ]
    assert analysis_variant(demodulated) == "nside64_baselines60s_demodulated"
    assert fixed_pass_variant_names(config) == ["nside64_baselines60s"]
    nearest = deep_merge(demodulated, {"simulation": {"sky_scanning": "nearest_pixel"}})
    with pytest.raises(ConfigError, match="sky_scanning: nearest_pixel"):
        check_config(nearest)
    unbinned = deep_merge(demodulated, {"simulation": {"fixed_pass_demodulated": False}})
    with pytest.raises(ConfigError, match="fixed_pass_demodulated: False"):
        check_config(unbinned)
    with pytest.raises(ConfigError, match="needs the notch"):
        check_config(deep_merge(demodulated, {"notch": {"width_divisor": None}}))


def test_channels_without_systematics_can_be_sampled_slower(repo, monkeypatch):
    """simulation.sampling_rate_without_systematics_hz applies to the channels outside
    instrument.systematics_channels only; null leaves every channel at sampling_rate_hz."""
    from hwp_tes_systematics.config import channel, simulated_rate_hz

    monkeypatch.chdir(repo)
    config = load_config(repo / "config/config.yaml", repo / "config/one_year.yaml")
    lft, mft = channel(config, "L1-040"), channel(config, "M1-140")
    assert config["simulation"]["sampling_rate_without_systematics_hz"] == 10.0
    config["simulation"]["sampling_rate_without_systematics_hz"] = None
    assert simulated_rate_hz(config, lft) == simulated_rate_hz(config, mft) == 19.0
    config["simulation"]["sampling_rate_without_systematics_hz"] = 10.0
    assert simulated_rate_hz(config, lft) == 10.0
    assert simulated_rate_hz(config, mft) == 19.0
    config["simulation"]["sampling_rate_hz"] = None
    assert simulated_rate_hz(config, mft) == mft.sampling_rate_hz


def test_channel_a2_of_an_unknown_channel_is_an_error_naming_it():
    """channel_a2_k_cmb gave A_2 = 0 for a channel the instrument model lacks (or a name in
    the wrong case): now an error naming it, with the case hint."""
    from hwp_tes_systematics.config import default_config_path, load_config
    from hwp_tes_systematics.instrument.channels import InstrumentModelError
    from hwp_tes_systematics.simulation.channel_inputs import channel_a2_k_cmb

    config = load_config(default_config_path())
    assert channel_a2_k_cmb(config, "L1-040") == 0.0  # a known channel outside the systematics
    for name, hint in (("X9-999", "X9-999"), ("m1-140", "M1-140")):
        with pytest.raises(InstrumentModelError, match=hint):
            channel_a2_k_cmb(config, name)
