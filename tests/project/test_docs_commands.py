"""Commands the documentation shows, run as a user would: the troubleshooting after a hard
kill (docs/getting_started.md) and a supplied HWP curve table (docs/workflow/hwp_curves.md),
on the tiny configuration and the cheapest rule (hwp_power)."""

import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest
from helpers import make_workdir, tiny_configfiles

pytestmark = pytest.mark.slow

TARGET = "results/inputs/hwp_power.csv"


def snakemake(workdir, *arguments):
    """Snakemake as the pages write it (no --nolock: the lock is what is tested). Targets
    come before --configfile, which takes every file that follows it."""
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "--cores", "1", *arguments],
        cwd=workdir,
        check=False,
        capture_output=True,
        text=True,
    )


def test_unlock_and_rerun_incomplete_after_a_hard_kill(repo, tmp_path):
    """A run killed with SIGKILL leaves the lock and an incomplete job; the next run stops
    with "Directory cannot be locked"; `snakemake --unlock`, then `--rerun-incomplete`,
    finish the job."""
    workdir = make_workdir(repo, tmp_path / "work")
    config = ("--configfile", *tiny_configfiles(repo))
    running = subprocess.Popen(
        [sys.executable, "-m", "snakemake", "--cores", "1", TARGET, *config],
        cwd=workdir,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: the job dies with it
    )
    incomplete = workdir / ".snakemake/incomplete"
    deadline = time.monotonic() + 300
    try:
        while not (incomplete.is_dir() and any(incomplete.iterdir())):
            assert running.poll() is None, "the run ended before its job could be killed"
            assert time.monotonic() < deadline, "no job started within 300 s"
            time.sleep(0.05)
    finally:
        os.killpg(running.pid, signal.SIGKILL)
        running.wait()
    assert any((workdir / ".snakemake/locks").iterdir()), "a hard kill leaves the lock"

    locked = snakemake(workdir, TARGET, *config)
    assert locked.returncode != 0
    assert "Directory cannot be locked" in locked.stdout + locked.stderr

    unlocked = snakemake(workdir, *config, "--unlock")
    assert unlocked.returncode == 0, unlocked.stderr[-3000:]
    rerun = snakemake(workdir, TARGET, "--rerun-incomplete", *config)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert (workdir / TARGET).stat().st_size > 0
    assert not any(incomplete.iterdir()) if incomplete.is_dir() else True


def test_supplied_hwp_curves_are_used(repo, tmp_path):
    """`snakemake --configfile my_hwp.yaml` with `optics.telescopes.MFT.hwp_curves_csv`
    pointing at a table of one's own: the MFT channels' HWP power follows it, the other
    telescopes' does not move."""
    workdir = make_workdir(repo, tmp_path / "work")
    config = ("--configfile", *tiny_configfiles(repo))
    shipped = snakemake(workdir, TARGET, *config)
    assert shipped.returncode == 0, shipped.stderr[-3000:]
    before = pd.read_csv(workdir / TARGET, comment="#").set_index("channel")

    lines = (workdir / "config/hwp/mft_hwp_curves.csv").read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("freq_ghz"))
    rows = [line.split(",") for line in lines[header + 1 :] if line.strip()]
    mine = [lines[header]] + [
        ",".join([f, str(0.5 * float(a_c)), a_i, t_c, t_i]) for f, a_c, a_i, t_c, t_i in rows
    ]  # the capacitive axis absorbs half as much (a + t <= 1 still holds)
    (workdir / "my_mft_hwp_curves.csv").write_text("\n".join(mine) + "\n")
    (workdir / "my_hwp.yaml").write_text(
        "optics:\n  telescopes:\n    MFT:\n      hwp_curves_csv: my_mft_hwp_curves.csv\n"
    )
    supplied = snakemake(workdir, TARGET, *config, "my_hwp.yaml")  # merged in order
    assert supplied.returncode == 0, supplied.stderr[-3000:]
    after = pd.read_csv(workdir / TARGET, comment="#").set_index("channel")

    a2 = "a2_w"  # A_2 [W], the HWPSS amplitude
    mft = [c for c in before.index if c.startswith("M")]
    others = [c for c in before.index if not c.startswith("M")]
    assert mft, before.index
    for channel in mft:
        assert after.loc[channel, a2] != pytest.approx(before.loc[channel, a2], rel=1e-3, abs=0)
    for channel in others:
        assert after.loc[channel, a2] == pytest.approx(before.loc[channel, a2], rel=1e-12, abs=0)
