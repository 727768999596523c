rule kw_conversion:
    """Power-to-temperature factor C = delta T / delta P_opt [K/W] per channel and A_2 in
    K_CMB. No wildcards."""
    input:
        hwp_power=paths.HWP_POWER_TABLE,
        curves=hwp_curve_files(),
    output:
        table=paths.KW_CONVERSION_TABLE,
    log:
        paths.log("kw_conversion"),
    params:
        instrument=config["instrument"],
        optics=config["optics"],
        kw_conversion=config["kw_conversion"],
    script:
        "../scripts/kw_conversion.py"
