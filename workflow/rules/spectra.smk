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


rule residual_spectra_figure:
    """BB of the CMB residual of each case (means over seeds), the systematic alone at
    each sigma_g1, the noise and foreground residuals, beside the lensing and tensor BB.
    No wildcards."""
    input:
        **{
            case: expand(paths.RESIDUAL_SPECTRA, seed=SEEDS, case=case)
            for case in CASES
        },
        systematic=expand(paths.SYSTEMATIC_SPECTRA, seed=SEEDS),
    output:
        figure=report(
            paths.FIG_RESIDUAL_SPECTRA,
            caption="../report/residual_spectra.rst",
            category="3. Requirement",
        ),
        table=paths.RESIDUAL_SPECTRA_MEANS,
    log:
        paths.log("residual_spectra_figure"),
    params:
        config=config_sections("requirement"),
        cases=CASES,
    script:
        "../scripts/residual_spectra_figure.py"
