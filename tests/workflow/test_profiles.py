"""The Snakemake profiles parse, name only rules that exist, and give a valid DAG."""

import re
import subprocess
import sys

import pytest
import yaml
from helpers import make_workdir, tiny_configfiles

TINY_NODE_MEM_MB = 8000  # what a laptop-sized SLURM node can give one job


def rule_names(repo):
    names = set()
    for path in (repo / "workflow/rules").glob("*.smk"):
        names |= set(re.findall(r"^\s*rule (\w+):", path.read_text(), flags=re.MULTILINE))
    return names


def test_profiles_parse_and_name_existing_rules(repo):
    rules = rule_names(repo)
    assert {"pair_maps", "component_separation", "likelihood"} <= rules
    for name in ("default", "slurm"):
        profile = yaml.safe_load((repo / f"profiles/{name}/profile.yaml").read_text())
        assert isinstance(profile, dict) and profile
        for section in ("set-resources", "groups"):
            unknown = set(profile.get(section, {})) - rules
            assert not unknown, f"profiles/{name}: {section} names unknown rules {unknown}"
    slurm = yaml.safe_load((repo / "profiles/slurm/profile.yaml").read_text())
    assert slurm["executor"] == "slurm"
    assert {"slurm_account", "slurm_partition", "mem_mb", "runtime"} <= set(
        slurm["default-resources"]
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", ["default", "slurm"])
def test_profile_dry_run_on_tiny_config(repo, tmp_path, name):
    """Snakemake accepts the profile and the DAG it implies (the groups included) without
    a scheduler; tests/workflow/test_slurm.py runs the SLURM profile on a real one."""
    workdir = make_workdir(repo, tmp_path)
    result = subprocess.run(
        [sys.executable, "-m", "snakemake", "--profile", str(repo / "profiles" / name)]
        + ["--configfile", *tiny_configfiles(repo), "--dry-run"],
        cwd=workdir,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-4000:]
    # what each job asks the scheduler for fits a small node on the tiny config: memory
    # that the rules scale with nside and channels (CI's one-node cluster refused 32 GB)
    requests = re.findall(r"mem_mb=(\d+)", result.stdout + result.stderr)
    assert requests and max(map(int, requests)) <= TINY_NODE_MEM_MB, requests
