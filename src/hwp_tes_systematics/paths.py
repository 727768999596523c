"""Every output path of the workflow, made in one place.

Rules use these patterns (with Snakemake wildcards in braces); nothing else joins paths.
"""

RESULTS = "results"
LOGS = "logs"
BENCHMARKS = f"{RESULTS}/benchmarks"

# Stage: HWP power tables and K/W conversion
HWP_POWER_TABLE = f"{RESULTS}/inputs/hwp_power.csv"
KW_CONVERSION_TABLE = f"{RESULTS}/inputs/kw_conversion.csv"
TES_RESPONSE_TABLE = f"{RESULTS}/inputs/tes_response.csv"

# Stage: foreground maps per channel (band-integrated, beam-smoothed)
FOREGROUND_MAP = f"{RESULTS}/sky/foreground_{{channel}}.fits"

# Stage: per-(channel, seed) TOD -> notch -> binned maps and g1 templates
PAIR_MAPS = f"{RESULTS}/maps/{{channel}}/seed{{seed}}.h5"
# simulation.realizations = map_domain: the seed-independent TOD pass of a channel, one file
# per map-maker binned in it (variant: config.map_variant, e.g. nside64_baselines60s)
FIXED_PASS = f"{RESULTS}/maps/{{channel}}/fixed_pass_{{variant}}.h5"
# ... the common mask of the analysis, and each seed's a_lm of a channel (its maps stay in memory)
ANALYSIS_MASK = f"{RESULTS}/alms/analysis_mask.h5"
CHANNEL_ALMS = f"{RESULTS}/alms/{{channel}}/seed{{seed}}.h5"

# Stage: TOD figures and an example recording in litebird_sim's HDF5 format
TOD_SAMPLE = f"{RESULTS}/tod/{{channel}}_sample.h5"

# Stages: component separation, spectra, likelihood, requirement (per seed and case)
HILC = f"{RESULTS}/hilc/seed{{seed}}/{{case}}.h5"
RESIDUAL_SPECTRA = f"{RESULTS}/spectra/seed{{seed}}/{{case}}.csv"
SYSTEMATIC_SPECTRA = f"{RESULTS}/spectra/seed{{seed}}/systematic_only.csv"
INSTRUMENT_SPECTRA = f"{RESULTS}/spectra/seed{{seed}}/fixed_instruments.csv"
TEMPLATE_FIT = f"{RESULTS}/spectra/seed{{seed}}/template_fit.json"
NOISE_MODEL = f"{RESULTS}/spectra/noise_model.csv"
RESIDUAL_SPECTRA_MEANS = f"{RESULTS}/spectra/residual_bb_means.csv"
LIKELIHOOD = f"{RESULTS}/likelihood/seed{{seed}}.json"
DELTA_R_TABLE = f"{RESULTS}/delta_r.csv"
REQUIREMENT = f"{RESULTS}/requirement.json"
ANSWER_TABLE = f"{RESULTS}/answer.csv"  # the requirement and its checks in a few rows

# Stage: diagnosis of recordings (and the workflow's own example recording)
EXAMPLE_RECORDING = f"{RESULTS}/diagnose/example_recording.h5"
EXAMPLE_SKY = f"{RESULTS}/diagnose/example_sky.fits"
DIAGNOSIS = f"{RESULTS}/diagnose/{{recording}}/diagnosis.json"
DIAGNOSIS_REPORT = f"{RESULTS}/diagnose/{{recording}}/diagnosis.md"

# Figures (numbered as in the paper)
FIG1_HWP_CURVES = f"{RESULTS}/figures/fig1_hwp_absorption_transmission.png"
FIG2_HWP_DIFFERENTIAL = f"{RESULTS}/figures/fig2_hwp_differential_power.png"
FIG3_HWP_EMISSION = f"{RESULTS}/figures/fig3_hwp_emission_vs_sky.png"
FIG4_TES_RESPONSE = f"{RESULTS}/figures/fig4_tes_response.png"
FIG5_TOD_CHUNK = f"{RESULTS}/figures/fig5_tod_chunk_{{channel}}.png"
FIG6_TOD_SPECTRA = f"{RESULTS}/figures/fig6_tod_spectra_{{channel}}.png"
FIG_NOTCH_TRANSFER = f"{RESULTS}/figures/notch_transfer_function.png"
FIG_NOTCH_BB = f"{RESULTS}/figures/notch_effect_on_cmb_{{channel}}.png"
NOTCH_SPECTRA = f"{RESULTS}/maps/notch_effect_{{channel}}.csv"
FIG7_LIKELIHOODS = f"{RESULTS}/figures/fig7_likelihoods.png"
FIG8_REQUIREMENT = f"{RESULTS}/figures/fig8_requirement.png"
FIG_A2_SCALING = f"{RESULTS}/figures/requirement_vs_a2_scale.png"
FIG_ELL_DISTRIBUTION = f"{RESULTS}/figures/information_and_bias_vs_ell.png"
FIG_FIXED_INSTRUMENTS = f"{RESULTS}/figures/fixed_instruments.png"
FIG_RESIDUAL_SPECTRA = f"{RESULTS}/figures/residual_spectra_bb.png"


def log(rule: str, wildcards: str = "") -> str:
    """Log file of a rule (wildcards as a '{a}_{b}' pattern, optional)."""
    return f"{LOGS}/{rule}{'/' + wildcards if wildcards else ''}.log"


def benchmark(rule: str, wildcards: str = "") -> str:
    """Benchmark file of a rule."""
    return f"{BENCHMARKS}/{rule}{'/' + wildcards if wildcards else ''}.tsv"
