rule foreground_maps:
    """Band-integrated (pysm3), beam-smoothed foreground I, Q, U maps of every channel, K_CMB,
    Galactic, at the resolution the TODs scan; pysm3 d0s0 data if configured, otherwise the
    embedded offline templates (flagged in the FITS header). One job for all channels: at
    nside 64 a job's start-up costs more than a map (22 jobs took 6 min of CPU, one ~15 s);
    at nside 512 the job takes ~5 min. No wildcards."""
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
