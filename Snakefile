# LiteBIRD: HWP synchronous signal x TES nonlinearity -> requirement on sigma_g1.
# Stages live in workflow/rules (one file each); the physics in src/hwp_tes_systematics.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


from hwp_tes_systematics import paths
from hwp_tes_systematics.config import (
    analysis_lmax,
    analysis_variant,
    check_config,
    demodulated_variants,
    fixed_pass_baselines,
    fixed_pass_nsides,
    fixed_pass_variant_names,
    fixed_pass_variants,
    moments_variant,
    noise_shaping_siblings,
    selected_channels,
)
from hwp_tes_systematics.analysis.systematics import case_names

check_config(config, source="Snakemake config")


include: "workflow/rules/common.smk"


wildcard_constraints:
    channel="[LMH][1-4]-[0-9]{3}",
    seed=r"\d+",
    case=r"nosys|sigma[0-9.]+e[-+]?[0-9]+",
    variant=r"nside[0-9]+_(nobaselines|baselines[0-9.e+-]+s)(_demodulated)?",


include: "workflow/rules/hwp_power.smk"
include: "workflow/rules/kw_conversion.smk"
include: "workflow/rules/tes_response.smk"
include: "workflow/rules/sky.smk"
include: "workflow/rules/maps.smk"
include: "workflow/rules/tod_figures.smk"
include: "workflow/rules/notch.smk"
include: "workflow/rules/component_separation.smk"
include: "workflow/rules/spectra.smk"
include: "workflow/rules/likelihood.smk"
include: "workflow/rules/requirement.smk"
include: "workflow/rules/diagnose.smk"


rule all:
    input:
        paths.HWP_POWER_TABLE,
        paths.KW_CONVERSION_TABLE,
        paths.TES_RESPONSE_TABLE,
        paths.FIG1_HWP_CURVES,
        paths.FIG2_HWP_DIFFERENTIAL,
        paths.FIG3_HWP_EMISSION,
        paths.FIG4_TES_RESPONSE,
        paths.REQUIREMENT,
        paths.FIG_RESIDUAL_SPECTRA,
        expand(paths.DIAGNOSIS, recording=RECORDINGS),
        rules.tod_figures.output,
        rules.notch_effect.output,
