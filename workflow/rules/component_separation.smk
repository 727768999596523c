rule component_separation:
    """Harmonic ILC over all channels of realization `seed`, for every case (nosys and each
    sigma<value>: maps = nosys + sigma sum_k z_k T_k on the systematics channels); the CMB
    residual and its foreground part as a_lm, one file per case. One job per seed, so the
    references' a_lm (the same in every case) are computed once. Wildcard: seed."""
    input:
        unpack(channel_maps_of_seed),
    output:
        hilc=expand(paths.HILC, case=CASES, allow_missing=True),
    log:
        paths.log("component_separation", "seed{seed}"),
    benchmark:
        paths.benchmark("component_separation", "seed{seed}")
    resources:
        mem_mb=component_separation_mem_mb,
    params:
        config=analysis_config(),
        cases=CASES,
    script:
        "../scripts/component_separation.py"
