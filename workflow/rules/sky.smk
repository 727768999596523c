rule foreground_maps:
    """Band-integrated (pysm3), beam-smoothed foreground I, Q, U maps of every channel, K_CMB,
    Galactic; pysm3 d0s0 data if configured, otherwise the embedded offline templates
    (flagged in the FITS header). No wildcards."""
    output:
        maps=expand(paths.FOREGROUND_MAP, channel=CHANNELS),
    log:
        paths.log("foreground_maps"),
    benchmark:
        paths.benchmark("foreground_maps")
    params:
        config=pass_config(),
        channels=CHANNELS,
    script:
        "../scripts/foreground_maps.py"
