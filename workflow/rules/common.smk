# Helpers shared by the stage files: inputs and settings that depend on the configuration.


def hwp_curve_files():
    """The HWP curve tables named in the config (rerun the HWP stage when one changes)."""
    telescopes = config["optics"]["telescopes"].values()
    return [t["hwp_curves_csv"] for t in telescopes if t["hwp_curves_csv"] is not None]


CHANNELS = selected_channels(config)
SEEDS = list(range(config["simulation"]["seeds"]))


def config_sections(*keys):
    """Only these sections of the config: a rule's params hold what it uses, so an edit
    elsewhere (e.g. a figure setting) does not rerun it."""
    return {key: config[key] for key in keys}


def simulation_config():
    """The config sections a simulation job depends on (a change reruns the job)."""
    keys = ("master_seed", "instrument", "simulation", "notch", "maps")
    return {key: config[key] for key in keys}


def pair_maps_mem_mb(wildcards, attempt):
    """Memory of one (channel, seed) job: one chunk of TOD and pointing, plus the maps."""
    samples = 31.0 * min(
        config["simulation"]["chunk_duration_s"],
        config["simulation"]["duration_days"] * 86400.0,
    )
    chunk_mb = 2 * samples * 8 * 40 / 2**20  # ~40 doubles per detector-sample in flight
    maps_mb = 12 * config["maps"]["nside"] ** 2 * 8 * 20 / 2**20
    return int(1500 + chunk_mb + maps_mb) * attempt


def component_separation_mem_mb(wildcards, attempt):
    """Memory of one seed's HILC: every channel's maps held at once (~60 doubles per pixel
    per channel: > 22 GB measured for 22 channels at nside 512, map_level_cost.py)."""
    maps_mb = len(CHANNELS) * 12 * config["maps"]["nside"] ** 2 * 60 * 8 / 2**20
    return int(1000 + maps_mb) * attempt


CASES = case_names(config["requirement"]["sigma_g1_per_k"])


def analysis_config():
    """The config the map-level analysis (HILC, spectra) depends on: a change elsewhere
    (figures, likelihood, budget) does not rerun it."""
    keys = ("master_seed", "instrument", "maps", "component_separation")
    requirement = {
        key: config["requirement"][key] for key in ("sigma_g1_per_k", "g1_per")
    }
    simulation = {"cmb_r": config["simulation"]["cmb_r"]}  # the input CMB of a seed
    return {
        **{key: config[key] for key in keys},
        "requirement": requirement,
        "simulation": simulation,
    }


def all_channel_maps():
    """{seed: {channel: maps file}} for every realization (the requirement's grid extension)."""
    return {
        seed: {
            channel: paths.PAIR_MAPS.format(channel=channel, seed=seed)
            for channel in CHANNELS
        }
        for seed in SEEDS
    }


def channel_maps_of_seed(wildcards):
    """{channel: maps file} of realization ``seed`` for all channels."""
    return {
        channel: paths.PAIR_MAPS.format(channel=channel, seed=wildcards.seed)
        for channel in CHANNELS
    }


def spectra_of_seed(wildcards):
    """{case: residual spectra file} of realization ``seed``."""
    return {
        case: paths.RESIDUAL_SPECTRA.format(seed=wildcards.seed, case=case)
        for case in CASES
    }


RECORDINGS = ["example", *config["diagnose"]["recordings"]]


def recording_inputs(wildcards):
    """{recording, sky} files of a recording named in diagnose.recordings, or the example."""
    if wildcards.recording == "example":
        return {"recording": paths.EXAMPLE_RECORDING, "sky": paths.EXAMPLE_SKY}
    return dict(config["diagnose"]["recordings"][wildcards.recording])
