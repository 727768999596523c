rule example_recording:
    """An example recording of diagnose.example_channel with the electrothermal TES
    nonlinearity and its own noise, and the sky map it saw. No wildcards; no input file:
    its K/W and A_2 come from the configured optics (channel_inputs.channel_conversion,
    the same numbers as the kw_conversion table; its config sections rerun it)."""
    output:
        recording=paths.EXAMPLE_RECORDING,
        sky=paths.EXAMPLE_SKY,
    log:
        paths.log("example_recording"),
    params:
        config=config_sections(
            "master_seed",
            "instrument",
            "optics",
            "kw_conversion",
            "tes",
            "simulation",
            "maps",
            "diagnose",
        ),
    script:
        "../scripts/example_recording.py"


rule diagnose:
    """Locate where a recording and its simulation differ, name the missing physics, fit it
    and report. Wildcards: recording (a name of diagnose.recordings, or "example")."""
    input:
        unpack(recording_inputs),
    output:
        diagnosis=paths.DIAGNOSIS,
        report=report(
            paths.DIAGNOSIS_REPORT,
            caption="../report/diagnosis.rst",
            category="4. Diagnosis",
        ),
    log:
        paths.log("diagnose", "{recording}"),
    benchmark:
        paths.benchmark("diagnose", "{recording}")
    params:
        config=config_sections("instrument", "optics", "kw_conversion", "diagnose"),
    script:
        "../scripts/diagnose.py"
