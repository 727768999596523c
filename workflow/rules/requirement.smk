rule requirement:
    """Mean delta r over seeds versus sigma_g1 by the paper's estimator (|r_sys - r_nosys|,
    grid extended downwards from the maps until two points are quadratic) and by the
    systematic-only one (the Fisher peak shift k sigma^2 and the 68 %-point shift); the
    requirement on sigma_g1 from each, whether sigma^2 holds, and the systematic-only
    requirement versus the A_2 scale; whether the likelihood model describes the data
    (per multipole bin); where in ell the information and the bias come from; the
    paper's Figs. 7 and 8; the bias of fixed instruments (g1 held over every seed, the
    term linear in g1 included) and their requirements; the requirement after the template
    fit (mitigation.template_fit) and the g1 it recovers. No wildcards."""
    input:
        **MASK_INPUT,
        likelihoods=expand(paths.LIKELIHOOD, seed=SEEDS),
        nosys_spectra=expand(paths.RESIDUAL_SPECTRA, seed=SEEDS, case="nosys"),
        systematic=expand(paths.SYSTEMATIC_SPECTRA, seed=SEEDS),
        instruments=expand(paths.INSTRUMENT_SPECTRA, seed=SEEDS),
        template_fits=expand(paths.TEMPLATE_FIT, seed=SEEDS),
        noise_model=paths.NOISE_MODEL,
        maps=[path for seed in SEEDS for path in all_channel_maps()[seed].values()],
    output:
        table=report(
            paths.DELTA_R_TABLE,
            caption="../report/delta_r.rst",
            category="3. Requirement",
        ),
        requirement=paths.REQUIREMENT,
        answer=report(
            paths.ANSWER_TABLE,
            caption="../report/answer.rst",
            category="0. The answer",
        ),
        fig_likelihoods=report(
            paths.FIG7_LIKELIHOODS,
            caption="../report/fig7.rst",
            category="3. Requirement",
        ),
        fig_requirement=report(
            paths.FIG8_REQUIREMENT,
            caption="../report/fig8.rst",
            category="0. The answer",
        ),
        fig_a2_scaling=report(
            paths.FIG_A2_SCALING,
            caption="../report/a2_scaling.rst",
            category="3. Requirement",
        ),
        fig_ell_distribution=report(
            paths.FIG_ELL_DISTRIBUTION,
            caption="../report/ell_distribution.rst",
            category="3. Requirement",
        ),
        fig_fixed_instruments=report(
            paths.FIG_FIXED_INSTRUMENTS,
            caption="../report/fixed_instruments.rst",
            category="3. Requirement",
        ),
    log:
        paths.log("requirement"),
    params:
        config={
            key: config[key]
            for key in (
                "master_seed",
                "instrument",
                "optics",
                "simulation",
                "notch",
                "maps",
                "component_separation",
                "likelihood",
                "requirement",
                "mitigation",
            )
        },
        map_paths=all_channel_maps(),
    script:
        "../scripts/requirement.py"
