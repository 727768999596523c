rule requirement:
    """Mean delta r = |r_sys - r_nosys| over seeds versus sigma_g1, the fit k sigma^2 and the
    sigma_g1 that meets the budget; the paper's Figs. 7 and 8. No wildcards."""
    input:
        likelihoods=expand(paths.LIKELIHOOD, seed=SEEDS),
    output:
        table=paths.DELTA_R_TABLE,
        requirement=paths.REQUIREMENT,
        fig_likelihoods=report(paths.FIG7_LIKELIHOODS, category="3. Requirement"),
        fig_requirement=report(paths.FIG8_REQUIREMENT, category="3. Requirement"),
    log:
        paths.log("requirement"),
    params:
        config=config,
    script:
        "../scripts/requirement.py"
