rule likelihood:
    """r at the 68% point of the Hamimeche-Lewis likelihood for every case of realization
    `seed`, on one r grid. Wildcards: seed."""
    input:
        unpack(spectra_of_seed),
        noise_model=paths.NOISE_MODEL,
    output:
        result=paths.LIKELIHOOD,
    log:
        paths.log("likelihood", "seed{seed}"),
    params:
        config={key: config[key] for key in ("likelihood", "requirement")},
        cases=CASES,
    script:
        "../scripts/likelihood.py"
