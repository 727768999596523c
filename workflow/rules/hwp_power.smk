rule hwp_power:
    """HWP emission and transmitted load per axis, Delta P_HWP and A_2 [W] for every channel;
    the paper's Figs. 1-3. No wildcards."""
    input:
        curves=hwp_curve_files(),
    output:
        table=paths.HWP_POWER_TABLE,
        fig_curves=paths.FIG1_HWP_CURVES,
        fig_differential=paths.FIG2_HWP_DIFFERENTIAL,
        fig_emission=paths.FIG3_HWP_EMISSION,
    log:
        paths.log("hwp_power"),
    params:
        instrument=config["instrument"],
        optics=config["optics"],
    script:
        "../scripts/hwp_power.py"
