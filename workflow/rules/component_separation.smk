rule component_separation:
    """Harmonic ILC over all channels of realization `seed`, for every case (nosys and each
    sigma<value>: maps = nosys + sigma sum_k z_k T_k on the systematics channels); the CMB
    residual and its foreground part as a_lm, one file per case; and the BB and EE cross
    spectra of the systematic's three terms (s^2, s h, h^2 of d^2) at sigma_g1 = 1 through
    the no-systematics weights (the systematic-only estimator); for each fixed instrument
    (g1 draws the same for every seed) the systematic's BB and its cross spectrum with the
    no-systematics residual. One job per seed, so the maps are read and the references'
    a_lm computed once; the template fit of mitigation.template_fit (each systematics
    channel's known templates fitted to its a_lm): what it leaves of the systematic and
    takes from the sky, through the no-systematics weights, and its fitted g1. Wildcard:
    seed."""
    input:
        unpack(channel_maps_of_seed),
    output:
        hilc=expand(paths.HILC, case=CASES, allow_missing=True),
        systematic=paths.SYSTEMATIC_SPECTRA,
        instruments=paths.INSTRUMENT_SPECTRA,
        template_fit=paths.TEMPLATE_FIT,
    log:
        paths.log("component_separation", "seed{seed}"),
    benchmark:
        paths.benchmark("component_separation", "seed{seed}")
    resources:
        mem_mb=component_separation_mem_mb,
    params:
        config={**analysis_config(), "mitigation": config["mitigation"]},
        cases=CASES,
        fixed_instruments=config["requirement"]["fixed_instruments"],
    script:
        "../scripts/component_separation.py"
