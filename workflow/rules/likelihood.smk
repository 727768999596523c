rule likelihood:
    """r at the 68% point of the Hamimeche-Lewis likelihood for every case of realization
    `seed`, on one r grid, and the systematic-only bias k (delta r = k sigma^2).
    Wildcards: seed."""
    input:
        unpack(spectra_of_seed),
        noise_model=paths.NOISE_MODEL,
        systematic=paths.SYSTEMATIC_SPECTRA,
    output:
        result=paths.LIKELIHOOD,
    log:
        paths.log("likelihood", "seed{seed}"),
    params:
        config={
            "likelihood": config["likelihood"],
            "mitigation": config["mitigation"],
            "requirement": {
                key: config["requirement"][key]
                for key in ("sigma_g1_per_k", "a2_scale_factors", "delta_r_budget")
            },
        },
        cases=CASES,
    script:
        "../scripts/likelihood.py"
