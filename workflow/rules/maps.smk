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
