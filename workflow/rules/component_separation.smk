rule component_separation:
    """Harmonic ILC over all channels of realization `seed` for `case` (nosys or sigma<value>:
    maps = nosys + sigma sum_k z_k T_k on the systematics channels); the CMB residual and its
    foreground part as a_lm. Wildcards: seed, case."""
    input:
        unpack(channel_maps_of_seed),
    output:
        hilc=paths.HILC,
    log:
        paths.log("component_separation", "seed{seed}_{case}"),
    benchmark:
        paths.benchmark("component_separation", "seed{seed}_{case}")
    params:
        config=analysis_config(),
    script:
        "../scripts/component_separation.py"
