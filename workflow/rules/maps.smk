if config["simulation"]["realizations"] == "tod":

    rule pair_maps:
        """TOD of one detector pair (sky + dipole + HWPSS + noise), 2f HWPSS template removal,
        4f notch, and binned I, Q, U maps with the per-detector g1 templates, chunk by chunk.
        Wildcards: channel (instrument-model name), seed (realization number)."""
        input:
            kw_conversion=paths.KW_CONVERSION_TABLE,
            foreground=paths.FOREGROUND_MAP,
        output:
            maps=paths.PAIR_MAPS,
        log:
            paths.log("pair_maps", "{channel}_seed{seed}"),
        benchmark:
            paths.benchmark("pair_maps", "{channel}_seed{seed}")
        threads: 1
        resources:
            mem_mb=pair_maps_mem_mb,
        params:
            config=simulation_config(),
        script:
            "../scripts/pair_maps.py"

else:

    rule fixed_pass:
        """The seed-independent TOD of one channel (foregrounds + dipole + HWPSS, no CMB, no
        noise) through the same filter and binning, once: its maps and template terms, the
        HWPSS moments, and the filter's action on a reference CMB and noise realization;
        binned by every map-maker of simulation.fixed_pass_nsides x
        fixed_pass_baseline_lengths_s from the same TOD, one file each. Wildcards: channel.
        """
        input:
            kw_conversion=paths.KW_CONVERSION_TABLE,
            foreground=paths.FOREGROUND_MAP,
        output:
            fixed=expand(paths.FIXED_PASS, variant=VARIANTS, allow_missing=True),
        log:
            paths.log("fixed_pass", "{channel}"),
        benchmark:
            paths.benchmark("fixed_pass", "{channel}")
        threads: 1
        resources:
            mem_mb=fixed_pass_mem_mb,
        params:
            config=pass_config(),
            variants=VARIANTS,
        script:
            "../scripts/fixed_pass.py"

    rule analysis_mask:
        """The common mask of the analysis (observed by every channel, outside the Galactic
        cut, apodized) from the fixed passes: the seeds' a_lm are computed on it. No
        wildcards."""
        input:
            fixed=[analysis_fixed_pass(channel) for channel in CHANNELS],
        output:
            mask=paths.ANALYSIS_MASK,
        log:
            paths.log("analysis_mask"),
        params:
            config=config_sections("component_separation"),
        script:
            "../scripts/analysis_mask.py"

    rule map_domain_alms:
        """Every seed's a_lm of one channel from the channel's fixed pass: each seed's CMB
        and white noise added in the map domain (module map_domain), its maps reduced in
        memory to the a_lm the HILC combines (never written: ~0.8 GB per channel and seed
        at nside 512); one job per channel, as the seeds share the fixed pass's operators.
        The noise shaping pooled over the fixed passes of the channels that share it
        (simulation.noise_shaping_pooling). Wildcards: channel."""
        input:
            fixed=analysis_fixed_pass(),
            shared_moments=shared_moments_file(),
            mask=paths.ANALYSIS_MASK,
            pooled=noise_shaping_files,
        output:
            alms=expand(paths.CHANNEL_ALMS, seed=SEEDS, allow_missing=True),
        log:
            paths.log("map_domain_alms", "{channel}"),
        benchmark:
            paths.benchmark("map_domain_alms", "{channel}")
        threads: 1
        params:
            config={**analysis_config(), **simulation_config()},
            seeds=SEEDS,
        script:
            "../scripts/map_domain_alms.py"
