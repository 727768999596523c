rule hwp_power:
    """HWP emission and transmitted load per axis, Delta P_HWP and A_2 [W] for every channel;
    the paper's Figs. 1-3. No wildcards."""
    input:
        curves=hwp_curve_files(),
    output:
        table=paths.HWP_POWER_TABLE,
        fig_curves=report(
            paths.FIG1_HWP_CURVES,
            caption="../report/fig1.rst",
            category="1. Physical inputs",
        ),
        fig_differential=report(
            paths.FIG2_HWP_DIFFERENTIAL,
            caption="../report/fig2.rst",
            category="1. Physical inputs",
        ),
        fig_emission=report(
            paths.FIG3_HWP_EMISSION,
            caption="../report/fig3.rst",
            category="1. Physical inputs",
        ),
    log:
        paths.log("hwp_power"),
    params:
        instrument=config["instrument"],
        optics=config["optics"],
    script:
        "../scripts/hwp_power.py"
