"""The project's layering, checked on the source: stage jobs never reach ground truth or the generator, entry
points stay thin, functions stay readable, every config's parameters are validated at DAG start."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rigbuild.paths import PROJECT_ROOT

RIGBUILD = PROJECT_ROOT / "rigbuild"
SCRIPTS = PROJECT_ROOT / "scripts"
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))

#: entry points of the rules that run a pipeline stage (not the generator, the evaluation or the characters)
STAGE_SCRIPTS = ["calibrate.py", "reconstruct.py", "track.py", "personalize.py", "retarget.py", "retarget_seol.py",
                 "metrics.py", "report.py"]
#: packages that hold production code (everything but the generator and the ground-truth evaluation)
FORBIDDEN_FROM_STAGES = ("rigbuild.eval", "rigbuild.synth")


def _module_name(path: Path) -> str:
    rel = path.relative_to(PROJECT_ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every rigbuild module a file imports, at any depth of the file (function-level imports included)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("rigbuild")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rigbuild") and node.level == 0:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def _module_files() -> dict[str, Path]:
    return {_module_name(p): p for p in RIGBUILD.rglob("*.py")}


def _reachable(start: Path, modules: dict[str, Path]) -> dict[str, str]:
    """rigbuild modules reachable from ``start`` by imports -> the module that first imported each."""
    seen: dict[str, str] = {}
    todo = [(start, "<script>")]
    while todo:
        path, _ = todo.pop()
        for name in _imports(path):
            for cand in (name, name.rsplit(".", 1)[0]):
                if cand in modules and cand not in seen:
                    seen[cand] = _module_name(path) if path.is_relative_to(RIGBUILD) else path.name
                    todo.append((modules[cand], cand))
    return seen


@pytest.mark.parametrize("script", STAGE_SCRIPTS)
def test_stage_jobs_never_import_ground_truth_evaluation_or_the_generator(script):
    modules = _module_files()
    reach = _reachable(SCRIPTS / script, modules)
    bad = {m: by for m, by in reach.items() if m.startswith(FORBIDDEN_FROM_STAGES)}
    assert not bad, f"scripts/{script} reaches {bad} (module -> imported by)"


def test_synth_is_imported_only_by_the_generator_eval_and_tests():
    allowed_prefixes = ("rigbuild.synth", "rigbuild.eval")
    allowed_scripts = {"synth_session.py", "make_character.py"}
    offenders = []
    for path in list(RIGBUILD.rglob("*.py")) + list(SCRIPTS.glob("*.py")):
        name = _module_name(path) if path.is_relative_to(RIGBUILD) else path.name
        if name.startswith(allowed_prefixes) or name in allowed_scripts or name == "rigbuild.cli":
            continue
        if any(m.startswith("rigbuild.synth") for m in _imports(path)):
            offenders.append(str(path.relative_to(PROJECT_ROOT)))
    assert not offenders, offenders


def test_cli_imports_the_generator_only_inside_its_command():
    """``rigbuild synth`` is the generator's command: the module level of the CLI stays free of it."""
    tree = ast.parse((RIGBUILD / "cli.py").read_text())
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert not any(isinstance(n, ast.ImportFrom) and (n.module or "").startswith(FORBIDDEN_FROM_STAGES) for n in top)


@pytest.mark.parametrize("script", sorted(p.name for p in SCRIPTS.glob("*.py")))
def test_entry_points_are_thin(script):
    n = len((SCRIPTS / script).read_text().splitlines())
    assert n <= 30, f"scripts/{script} has {n} lines; move its logic into rigbuild/"


def test_no_function_over_120_lines():
    long = []
    for path in RIGBUILD.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 120:
                    long.append(f"{path.relative_to(PROJECT_ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


def test_no_stage_code_writes_the_session_metrics_file():
    """metrics.json is the output of one rule (``metrics``): no code merges into it."""
    for path in list(RIGBUILD.rglob("*.py")) + list(SCRIPTS.glob("*.py")):
        assert "merge_metrics" not in path.read_text(), path


def _dry_run(configfile: str, tmp_path: Path) -> subprocess.CompletedProcess:
    r = subprocess.run([SNAKEMAKE, "-n", "--cores", "1", "--snakefile", str(PROJECT_ROOT / "Snakefile"),
                        "--directory", str(tmp_path), "--configfile", str(configfile)],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    r.out = r.stdout + r.stderr
    return r


@pytest.mark.parametrize("configfile,session", [("config/ict.yaml", "ict"), ("config/ict-large.yaml", "ict_large")])
def test_tier_configs_plan_their_own_session_only(configfile, session, tmp_path):
    from rigbuild.paths import ict_dir

    if not (ict_dir() / "generic_neutral_mesh.obj").exists():
        pytest.skip(f"ICT-FaceKit not found at {ict_dir()} (set RIGBUILD_DATA)")
    r = _dry_run(str(PROJECT_ROOT / configfile), tmp_path)
    assert r.returncode == 0, r.out[-3000:]
    assert f"synth_session_{session}" in r.out
    assert "synth_session_demo" not in r.out and "results/demo" not in r.out


def test_the_demo_dev_config_plans_its_own_session_only(tmp_path):
    r = _dry_run(str(PROJECT_ROOT / "config" / "demo-dev.yaml"), tmp_path)
    assert r.returncode == 0, r.out[-3000:]
    assert "synth_session_demo_dev" in r.out and "results/demo_dev/" in r.out
    assert "results/demo/" not in r.out and "sessions/demo/" not in r.out


@pytest.mark.parametrize("block,typo,suggestion", [
    ({"track": {"lam_flw": 1.0}}, "params.track.lam_flw", "lam_flow"),
    ({"reconstruct": {"min_view": 2}}, "params.reconstruct.min_view", "min_views"),
    ({"personalize": {"held_out_sequence": ["rom00"]}}, "params.personalize.held_out_sequence", "held_out_sequences"),
    ({"retarget": {"seol": {"sparsty": 0.1}}}, "params.retarget.seol.sparsty", "sparsity"),
    ({"trak": {}}, "params.trak", "track"),
])
def test_a_parameter_typo_fails_at_dag_start_with_a_suggestion(block, typo, suggestion, tmp_path):
    base = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    base["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    base["params"] = {**base["params"], **block}
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump(base))
    r = _dry_run(str(cfg), tmp_path)
    out = r.out
    assert r.returncode != 0
    assert typo in out and f"did you mean '{suggestion}'" in out, out[-2000:]
