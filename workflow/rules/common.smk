# Helpers shared by the rule files: inputs that depend on the configuration.


def hwp_curve_files():
    """The HWP curve tables named in the config (rerun the HWP stage when one changes)."""
    telescopes = config["optics"]["telescopes"].values()
    return [t["hwp_curves_csv"] for t in telescopes if t["hwp_curves_csv"] is not None]
