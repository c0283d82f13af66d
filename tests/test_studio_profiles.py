"""Every Snakemake profile under workflow/profiles/ names only rules that exist in rules/*.smk (a resource set
for a misspelled rule is silently ignored by Snakemake, and the real rule runs on the default runtime)."""

from __future__ import annotations

import re

import pytest
import yaml

from rigbuild.paths import PROJECT_ROOT

PROFILES = sorted((PROJECT_ROOT / "workflow" / "profiles").glob("*/config.yaml"))
#: profile keys whose mapping is keyed by rule name (Snakemake's per-rule settings)
PER_RULE_KEYS = ("set-resources", "set-threads", "set-resource-scopes")


def rule_names() -> set[str]:
    """Rule names declared in Snakefile and rules/*.smk: ``rule <name>:`` and the generated
    ``name: f"<prefix>_{...}"`` rules (kept as ``<prefix>_*`` patterns)."""
    names: set[str] = set()
    for path in [PROJECT_ROOT / "Snakefile", *sorted((PROJECT_ROOT / "rules").glob("*.smk"))]:
        text = path.read_text()
        names |= set(re.findall(r"^\s*rule\s+([A-Za-z_]\w*)\s*:", text, flags=re.M))
        for prefix in re.findall(r"^\s*name:\s*\n\s*f[\"']([A-Za-z_]\w*?)\{", text, flags=re.M):
            names.add(prefix + "*")
    return names


def _known(name: str, names: set[str]) -> bool:
    return name in names or any(n.endswith("*") and name.startswith(n[:-1]) for n in names)


def test_rule_names_are_parsed():
    names = rule_names()
    assert {"reconstruct_frame", "track_sequence", "personalize", "synth_session_*", "all"} <= names
    assert "reconstruct" not in names


@pytest.mark.parametrize("profile", PROFILES, ids=lambda p: p.parent.name)
def test_profile_names_real_rules(profile):
    cfg = yaml.safe_load(profile.read_text()) or {}
    names = rule_names()
    for key in PER_RULE_KEYS:
        unknown = [r for r in (cfg.get(key) or {}) if not _known(str(r), names)]
        assert not unknown, f"{profile}: {key} names rules that do not exist: {unknown} (rules: {sorted(names)})"


def test_slurm_profile_sets_the_long_rules():
    cfg = yaml.safe_load((PROJECT_ROOT / "workflow" / "profiles" / "slurm" / "config.yaml").read_text())
    assert {"reconstruct_frame", "track_sequence", "personalize"} <= set(cfg["set-resources"])
