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
        HWPSS moments, and the filter's action on a reference CMB and noise realization.
        Wildcards: channel."""
        input:
            kw_conversion=paths.KW_CONVERSION_TABLE,
            foreground=paths.FOREGROUND_MAP,
        output:
            fixed=paths.FIXED_PASS,
        log:
            paths.log("fixed_pass", "{channel}"),
        benchmark:
            paths.benchmark("fixed_pass", "{channel}")
        threads: 1
        resources:
            mem_mb=pair_maps_mem_mb,
        params:
            config=simulation_config(),
        script:
            "../scripts/fixed_pass.py"

    rule map_domain_maps:
        """The maps file of every seed of one channel from the channel's fixed pass: each
        seed's CMB and white noise added in the map domain (module map_domain); one job per
        channel, as a seed costs less than starting a job. Wildcards: channel."""
        input:
            fixed=paths.FIXED_PASS,
        output:
            maps=expand(paths.PAIR_MAPS, seed=SEEDS, allow_missing=True),
        log:
            paths.log("map_domain_maps", "{channel}"),
        benchmark:
            paths.benchmark("map_domain_maps", "{channel}")
        threads: 1
        params:
            config=simulation_config(),
            seeds=SEEDS,
        script:
            "../scripts/map_domain_maps.py"
