rule notch_effect:
    """Noise-free CMB TOD of figures.tod_channel binned with and without the 4f notch: the
    filter's transfer function on the sky's EE and BB spectra. No wildcards."""
    output:
        spectra=expand(paths.NOTCH_SPECTRA, channel=config["figures"]["tod_channel"]),
        figure=report(
            expand(paths.FIG_NOTCH_BB, channel=config["figures"]["tod_channel"]),
            caption="../report/notch_effect.rst",
            category="2. TOD and maps",
        ),
    log:
        paths.log("notch_effect"),
    benchmark:
        paths.benchmark("notch_effect")
    params:
        config=simulation_config(),
        channel=config["figures"]["tod_channel"],
    script:
        "../scripts/notch_effect.py"
