"""The Snakemake profiles parse and name only rules that exist."""

import re

import yaml


def rule_names(repo):
    names = set()
    for path in (repo / "workflow/rules").glob("*.smk"):
        names |= set(re.findall(r"^rule (\w+):", path.read_text(), flags=re.MULTILINE))
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
