"""Helpers of the tests: a copy of the workflow in a temp dir, the Snakemake runner and the
command-line runner."""

import shutil
import subprocess
import sys

# the tests' workflow runs: the one-day machinery (config/one_day.yaml) at tiny size
TINY_CONFIGS = ("config/one_day.yaml", "tests/configs/tiny.yaml")
TINY_DEFAULT = "tests/configs/tiny_default.yaml"  # the embedded default's path at tiny size


def tiny_configfiles(repo) -> list[str]:
    """The tiny test configuration's files, in merge order (after the embedded default)."""
    return [str(repo / name) for name in TINY_CONFIGS]


def make_workdir(repo, workdir):
    """A copy of the workflow (Snakefile, rules, scripts, config) in ``workdir``."""
    workdir.mkdir(parents=True, exist_ok=True)
    for item in ("Snakefile", "workflow", "config"):
        source = repo / item
        if source.is_dir():
            shutil.copytree(source, workdir / item)
        else:
            shutil.copy(source, workdir / item)
    return workdir


def snakemake(workdir, *targets, extra=()):
    """Run Snakemake (1 core unless ``extra`` says otherwise) and return the CompletedProcess."""
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", "--nolock", *extra, *targets],
        cwd=workdir,
        check=False,
        capture_output=True,
        text=True,
    )


def run_cli(cwd, *arguments) -> subprocess.CompletedProcess:
    """``python -m hwp_tes_systematics ARGUMENTS`` run in the folder ``cwd``."""
    return subprocess.run(
        [sys.executable, "-m", "hwp_tes_systematics", *map(str, arguments)],
        cwd=cwd,
        check=False,
        capture_output=True,
        text=True,
    )


def m1_140_a2_k() -> float:
    """M1-140's nominal HWPSS amplitude A_2 [K_CMB] from the default configuration's optics
    (the diagnosis testbed's nominal values, computed once)."""
    from hwp_tes_systematics.diagnose.testbed import nominal

    return nominal("M1-140")["a2_k"]


def m1_140_pair(duration_s, chunk_s, nside, rate_hz=None, noise_model="toast"):
    """The M1-140 detector pair's simulator from 2032-04-01 over ``duration_s`` in chunks of
    ``chunk_s`` at ``rate_hz`` (default the instrument model's) and ``nside``."""
    from hwp_tes_systematics.instrument import load_channel
    from hwp_tes_systematics.simulation.tod import MissionPlan, PairSimulator

    channel = load_channel("M1-140")
    plan = MissionPlan(
        "2032-04-01T00:00:00", duration_s, chunk_s, rate_hz or channel.sampling_rate_hz
    )
    return PairSimulator(channel, plan, nside, noise_model=noise_model)


def pipeline_settings(simulator, **changes):
    """The map-making settings of config/one_year.yaml for ``simulator`` (the paper's notch
    with 1200 s margins, 60 s baselines, M1-140's A_2), with ``changes``."""
    from hwp_tes_systematics.simulation.tod_maps import PairMapSettings

    values = {
        "master_seed": 7,
        "seed": 0,
        "nside": simulator.nside,
        "plan": simulator.plan,
        "a2_k_cmb": m1_140_a2_k(),
        "notch_width_divisor": 100.0,
        "notch_margin_s": 1200.0,
        "max_condition_number": 100.0,
        "baseline_length_s": 60.0,
    }
    return PairMapSettings(**(values | changes))


def gain_sidebands(
    n, rate_hz, seed, amplitude_k=0.3, gain_amplitude=6e-3, slope=1.0, carrier_hz=1.3
):
    """A gain fluctuation's part of a residual, A g(t) cos(2 pi f_0 t) [K]: g Gaussian with
    P_g = a^2 (10 mHz / f)^beta (diagnose.fluctuations.gain_psd; rfft variance P_g f_s n / 2)."""
    import numpy as np
    import scipy.fft

    from hwp_tes_systematics.diagnose.effects.fluctuations import gain_psd

    rng = np.random.default_rng(seed)
    freqs = scipy.fft.rfftfreq(n, 1 / rate_hz)
    power = gain_psd(freqs, gain_amplitude, slope, rate_hz / n) * rate_hz * n / 2
    power[0] = 0.0
    modes = np.sqrt(power / 2) * (
        rng.standard_normal(freqs.size) + 1j * rng.standard_normal(freqs.size)
    )
    g = scipy.fft.irfft(modes, n=n)
    return amplitude_k * g * np.cos(2 * np.pi * carrier_hz * np.arange(n) / rate_hz)


def qu_rms(maps, good) -> float:
    """The rms of a (3, npix) map's Q and U over the pixels ``good``."""
    import numpy as np

    return float(np.sqrt(np.mean(maps[1:, good] ** 2)))


def sh_noise_ratio(full, noisy, noiseless, noise_scale, seeds, detector, good) -> float:
    """The s h term's noise of ``detector`` (its noisy minus noiseless term, Q/U rms,
    mean over ``seeds``), map domain over full path: ``full`` {(seed, noise scale): the
    full path's maps}, ``noisy``, ``noiseless`` {seed: the map domain's maps}."""
    import numpy as np

    def noise(maps, quiet):
        return qu_rms(
            maps["template_terms"][1, detector] - quiet["template_terms"][1, detector], good
        )

    simulated = np.mean([noise(full[s, noise_scale], full[s, 0.0]) for s in seeds])
    drawn = np.mean([noise(noisy[s], noiseless[s]) for s in seeds])
    return drawn / simulated


def map_noise_band_ratios(full, noisy, fixed, noise_scale, seeds, lmax, bands):
    """(n_bands, 2) the map's E and B noise power per multipole band (nosys minus the CMB
    reference and the fixed pass's nosys, on the fixed pass's good pixels, mean over
    ``seeds``), map domain (``noisy`` {seed: maps}) over full path (``full``)."""
    import healpy as hp
    import numpy as np

    good = fixed.good

    def spectrum(nosys, cmb_reference):
        noise = np.where(good, nosys - cmb_reference - fixed.nosys, 0.0)
        return hp.anafast(noise, lmax=lmax)[1:3]

    simulated = np.mean(
        [
            spectrum(full[s, noise_scale]["nosys"], full[s, noise_scale]["references"][0])
            for s in seeds
        ],
        axis=0,
    )
    drawn = np.mean([spectrum(noisy[s]["nosys"], noisy[s]["cmb_reference"]) for s in seeds], axis=0)
    return np.array([drawn[:, a:b].sum(axis=1) / simulated[:, a:b].sum(axis=1) for a, b in bands])
