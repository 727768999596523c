rule tod_figures:
    """A few hours of TOD of figures.tod_channel with and without nonlinearity (paper Figs. 5
    and 6) and the notch transfer function. No wildcards."""
    input:
        kw_conversion=paths.KW_CONVERSION_TABLE,
    output:
        fig_chunk=report(
            paths.FIG5_TOD_CHUNK.format(channel=config["figures"]["tod_channel"]),
            caption="../report/fig5.rst",
            category="2. TOD and maps",
        ),
        fig_spectra=report(
            paths.FIG6_TOD_SPECTRA.format(channel=config["figures"]["tod_channel"]),
            caption="../report/fig6.rst",
            category="2. TOD and maps",
        ),
        fig_notch=report(
            paths.FIG_NOTCH_TRANSFER,
            caption="../report/notch_transfer.rst",
            category="2. TOD and maps",
        ),
    log:
        paths.log("tod_figures"),
    params:
        config=simulation_config() | {"figures": config["figures"]},
    script:
        "../scripts/tod_figures.py"
