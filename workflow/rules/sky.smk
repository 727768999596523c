rule foreground_maps:
    """Band-integrated (pysm3), beam-smoothed foreground I, Q, U maps of one channel, K_CMB,
    Galactic, at the resolution the TODs scan; pysm3 d0s0 data if configured, otherwise the
    embedded offline templates (flagged in the FITS header). One job per channel, so that a
    channel's fixed pass starts as soon as its map exists (~14 s each at nside 512).
    Wildcards: channel."""
    output:
        maps=paths.FOREGROUND_MAP,
    log:
        paths.log("foreground_maps", "{channel}"),
    benchmark:
        paths.benchmark("foreground_maps", "{channel}")
    params:
        config=pass_config(),
    script:
        "../scripts/foreground_maps.py"
