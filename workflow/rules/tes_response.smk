rule tes_response:
    """Electrothermal TES model at each channel's nominal load: responsivity, saturation
    and the g1 [1/K], g2 [1/K^2] of its expansion; the paper's Fig. 4. No wildcards."""
    input:
        kw_conversion=paths.KW_CONVERSION_TABLE,
    output:
        table=paths.TES_RESPONSE_TABLE,
        figure=report(
            paths.FIG4_TES_RESPONSE,
            caption="../report/fig4.rst",
            category="1. Physical inputs",
        ),
    log:
        paths.log("tes_response"),
    params:
        tes=config["tes"],
    script:
        "../scripts/tes_response.py"
