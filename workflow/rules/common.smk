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


def pass_config():
    """simulation_config() as the foregrounds and the fixed passes see it: the sky's
    resolution is the scan's and the map-makers are the pass's list, so that running the
    analysis at another of them (maps.nside, maps.baseline_length_s) reruns neither."""
    passed = simulation_config()
    primary_nside, primary_baseline = fixed_pass_variants(config)[0]
    passed["maps"] = {
        **config["maps"],
        "nside": primary_nside,
        "baseline_length_s": primary_baseline,
    }
    passed["simulation"] = {
        **config["simulation"],
        "fixed_pass_nsides": fixed_pass_nsides(config),
        "fixed_pass_baseline_lengths_s": fixed_pass_baselines(config),
    }
    # the seeds' choice, not the pass's: changing it reruns no fixed pass
    del passed["simulation"]["noise_shaping_pooling"]
    return passed


# the map-makers of a fixed pass, and the one the analysis reads
VARIANTS = fixed_pass_variant_names(config)
ANALYSIS_VARIANT = analysis_variant(config)


def analysis_fixed_pass(channel="{channel}"):
    """The fixed pass file the analysis reads (of ``channel``, or its wildcard)."""
    return paths.FIXED_PASS.format(channel=channel, variant=ANALYSIS_VARIANT)


def noise_shaping_files(wildcards):
    """The analysis fixed pass files whose noise shaping a channel's seeds pool
    (config.noise_shaping_siblings: its own alone, or its telescope's)."""
    return [
        analysis_fixed_pass(name)
        for name in noise_shaping_siblings(config, wildcards.channel)
    ]


def shared_moments_file(channel="{channel}"):
    """[the fixed pass file that holds the HWPSS moments of the analysis's resolution], or
    [] when the analysis's own file holds them."""
    holder = paths.FIXED_PASS.format(
        channel=channel, variant=moments_variant(config, config["maps"]["nside"])
    )
    return [] if holder == analysis_fixed_pass(channel) else [holder]


def chunk_samples():
    """Samples of one detector in a chunk, at the PTEP rate (31 Hz, an upper bound)."""
    return 31.0 * min(
        config["simulation"]["chunk_duration_s"],
        config["simulation"]["duration_days"] * 86400.0,
    )


def pair_maps_mem_mb(wildcards, attempt):
    """Memory of one (channel, seed) job: one chunk of TOD and pointing, plus the maps."""
    chunk_mb = (
        2 * chunk_samples() * 8 * 40 / 2**20
    )  # ~40 doubles per detector-sample in flight
    maps_mb = 12 * config["maps"]["nside"] ** 2 * 8 * 20 / 2**20
    return int(1500 + chunk_mb + maps_mb) * attempt


def fixed_pass_mem_mb(wildcards, attempt):
    """Memory of one fixed pass: a chunk in flight (~40 doubles per detector-sample, x 2
    with both baseline settings) and, per map-maker, its equations (~16 maps), moments
    and calibration (~40 doubles per pixel in all), solved at the end (x 2); each
    reference noise realization beyond the first adds n and h n: 2 TODs in flight, 4
    calibration maps (12 doubles per pixel); 2 GB of interpreter and libraries. The
    nside-512 run (passes at 22704d5, two realizations, one map-maker) peaked at 5.3-5.9
    GB per MFT/HFT pass against 6.3 GB asked. A demodulating map-maker adds its three
    streams of every TOD in flight (~30 doubles per detector-sample) and ~0.6 times a
    binned one's accumulations: the one-year demodulated pass at nside 512-64
    (H1-280, session 27) peaked at 8.0 GB against 8.9 GB asked (11.2 GB with the
    factor 2.5 estimated before, which let one such pass run at a time on 20 GB)."""
    offsets = len(set(b is None for b in fixed_pass_baselines(config)))
    extra_realizations = config["simulation"]["noise_reference_realizations"] - 1
    demodulated = bool(demodulated_variants(config))
    per_sample = 40 + 2 * 2 * extra_realizations + 30 * demodulated
    chunk_mb = 2 * chunk_samples() * 8 * per_sample * offsets
    pixels = sum(12 * nside**2 for nside, _ in fixed_pass_variants(config))
    pixels *= 1.6 if demodulated else 1.0
    per_pixel = 40 + 12 * extra_realizations
    return int(2000 + chunk_mb / 2**20 + 2 * pixels * per_pixel * 8 / 2**20) * attempt


def component_separation_mem_mb(wildcards, attempt):
    """Memory of one seed's HILC: one channel's maps at a time (~60 doubles per pixel, TOD
    path; none on the map-domain path, which reads a_lm) and every channel's a_lm (4
    kinds, 3 template terms per detector of a pair, their sums and each detector's whole
    template: ~14 sets of 3 complex a_lm up to the analysis lmax)."""
    nside = config["maps"]["nside"]
    lmax = analysis_lmax(config)
    maps_mb = 0 if MAP_DOMAIN else 12 * nside**2 * 60 * 8 / 2**20
    alms_mb = (
        len(CHANNELS) * 14 * 3 * (lmax + 1) ** 2 / 2 * 16 * 3 / 2**20
    )  # x3: copies
    return int(1000 + maps_mb + alms_mb) * attempt


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


# what a seed's HILC reads of each channel: its maps file (TOD path) or its a_lm on the
# analysis mask (map-domain path, whose seeds' maps never reach the disk)
MAP_DOMAIN = config["simulation"]["realizations"] == "map_domain"
CHANNEL_OF_SEED = paths.CHANNEL_ALMS if MAP_DOMAIN else paths.PAIR_MAPS
MASK_INPUT = {"mask": paths.ANALYSIS_MASK} if MAP_DOMAIN else {}


def all_channel_maps():
    """{seed: {channel: maps or a_lm file}} for every realization (the requirement's grid
    extension)."""
    return {
        seed: {
            channel: CHANNEL_OF_SEED.format(channel=channel, seed=seed)
            for channel in CHANNELS
        }
        for seed in SEEDS
    }


def channel_maps_of_seed(wildcards):
    """{channel: maps or a_lm file} of realization ``seed`` for all channels, and the
    analysis mask on the map-domain path."""
    return {
        **{
            channel: CHANNEL_OF_SEED.format(channel=channel, seed=wildcards.seed)
            for channel in CHANNELS
        },
        **MASK_INPUT,
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
