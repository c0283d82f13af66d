"""Rig and character sources are declared inputs: editing a character's OBJs reruns its character_rig job, and
the personalize job lists its template rig's files (Snakemake dry runs on the demo config)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

from rigbuild.io.rigs import load_rig, rig_source_files, write_obj_folder_rig
from rigbuild.paths import PROJECT_ROOT

SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))


def _dry_run(tmp_path: Path, config: dict, *targets: str) -> str:
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump(config))
    r = subprocess.run([SNAKEMAKE, "-n", "--configfile", str(cfg), "--directory", str(tmp_path), "--snakefile",
                        str(PROJECT_ROOT / "Snakefile"), "--cores", "1", *targets],
                       capture_output=True, text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=300)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-3000:]
    return out


def _config(tmp_path: Path, rig_folder: Path) -> dict:
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    cfg["characters"] = {"hero": {"rig": str(rig_folder), "kind": "template"}}
    return cfg


def _obj_rig(folder: Path) -> None:
    rig = load_rig("procedural")
    write_obj_folder_rig(rig.subset(rig.shape_names[:3]), folder)


def test_rig_source_files(tmp_path):
    _obj_rig(tmp_path / "hero")
    files = {Path(f).name for f in rig_source_files(tmp_path / "hero")}
    rig = load_rig(tmp_path / "hero")
    assert files == {"neutral.obj", "rig.json", *(f"{n}.obj" for n in rig.shape_names)}
    assert rig_source_files("procedural") == [] and rig_source_files(tmp_path / "nowhere") == []


def test_editing_a_character_obj_reruns_its_rig(tmp_path):
    rig_folder = tmp_path / "rigs" / "hero"
    _obj_rig(rig_folder)
    cfg = _config(tmp_path, rig_folder)
    target = "results/demo/characters/hero.npz"
    assert "character_rig" in _dry_run(tmp_path, cfg, target)
    out = tmp_path / target
    out.parent.mkdir(parents=True)
    out.write_bytes(b"built")
    now = time.time()
    for f in rig_folder.iterdir():
        os.utime(f, (now - 100, now - 100))
    os.utime(out, (now - 50, now - 50))
    assert "Nothing to be done" in _dry_run(tmp_path, cfg, target)
    shape = sorted(rig_folder.glob("*.obj"))[-1]
    os.utime(shape, (now, now))  # the artist re-exports one shape
    text = _dry_run(tmp_path, cfg, target)
    assert "character_rig" in text and shape.name in text


def test_personalize_declares_its_template_rig_files(tmp_path):
    rig_folder = tmp_path / "rigs" / "template"
    _obj_rig(rig_folder)
    cfg = _config(tmp_path, rig_folder)
    cfg["params"]["personalize"] = {**(cfg["params"].get("personalize") or {}), "template_rig": str(rig_folder)}
    text = _dry_run(tmp_path, cfg, "results/demo/personalize/rig.npz")
    job = text[text.index("rule personalize:"):]
    inputs = job[:job.index("\n", job.index("input:"))]
    assert str(rig_folder / "neutral.obj") in inputs and str(rig_folder / "rig.json") in inputs


def test_export_names_are_checked_at_dag_start(tmp_path):
    """``params.personalize.export: {names: ...}`` is validated with the other params before any job runs."""
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    cfg["params"]["personalize"] = {**(cfg["params"].get("personalize") or {}), "export": {"names": "arkit52"}}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    r = subprocess.run([SNAKEMAKE, "-n", "--configfile", str(tmp_path / "bad.yaml"), "--directory", str(tmp_path),
                        "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--cores", "1"],
                       capture_output=True, text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=300)
    assert r.returncode != 0
    assert "unknown export names 'arkit52'" in r.stdout + r.stderr and "arkit" in r.stdout + r.stderr
    cfg["params"]["personalize"]["export"] = {"names": "arkit"}
    assert "personalize" in _dry_run(tmp_path, cfg)
