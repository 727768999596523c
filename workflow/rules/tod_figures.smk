rule tod_figures:
    """A few hours of TOD of figures.tod_channel with and without nonlinearity (paper Figs. 5
    and 6) and the notch transfer function. No wildcards."""
    input:
        kw_conversion=paths.KW_CONVERSION_TABLE,
    output:
        fig_chunk=expand(paths.FIG5_TOD_CHUNK, channel=config["figures"]["tod_channel"]),
        fig_spectra=expand(
            paths.FIG6_TOD_SPECTRA, channel=config["figures"]["tod_channel"]
        ),
        fig_notch=paths.FIG_NOTCH_TRANSFER,
    log:
        paths.log("tod_figures"),
    params:
        config=simulation_config() | {"figures": config["figures"]},
    script:
        "../scripts/tod_figures.py"
