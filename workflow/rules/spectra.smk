rule residual_spectra:
    """EE and BB pseudo-spectra (f_sky corrected) of the CMB residual and of its foreground
    and noise parts. Wildcards: seed, case."""
    input:
        hilc=paths.HILC,
    output:
        spectra=paths.RESIDUAL_SPECTRA,
    log:
        paths.log("residual_spectra", "seed{seed}_{case}"),
    script:
        "../scripts/residual_spectra.py"


rule noise_model:
    """N_ell and C_FGres of the likelihood model: means over seeds of the no-systematics
    noise and foreground residual BB spectra. No wildcards."""
    input:
        spectra=expand(paths.RESIDUAL_SPECTRA, seed=SEEDS, case="nosys"),
    output:
        model=paths.NOISE_MODEL,
    log:
        paths.log("noise_model"),
    script:
        "../scripts/noise_model.py"
