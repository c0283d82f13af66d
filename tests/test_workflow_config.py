"""Bad configs and sessions fail at DAG start (dry run) with a message naming the file and field."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rigbuild.paths import PROJECT_ROOT

SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))


def _dry_run(tmp_path: Path, config: dict, *extra: str) -> subprocess.CompletedProcess:
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump(config))
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    r = subprocess.run([SNAKEMAKE, "-n", "--configfile", str(cfg), "--directory", str(tmp_path),
                           "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--cores", "1", *extra],
                          capture_output=True, text=True, env=env, timeout=300)
    r.out = r.stdout + r.stderr  # snakemake prints DAG-start errors to stdout
    return r


def _real_session(folder: Path, **overrides) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    data = {"name": "real", "cameras": ["a", "b"], "image_size": [640, 480],
            "board": {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 30,
                      "marker_size_mm": 22, "dictionary": "DICT_5X5_100"},
            "rom": [{"name": "s0", "frames": [0, 3]}]}
    data.update(overrides)
    (folder / "session.yaml").write_text(yaml.safe_dump(data))
    return folder


def test_default_config_dry_run_lists_the_dag(tmp_path):
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    r = _dry_run(tmp_path, cfg)
    assert r.returncode == 0, r.out[-3000:]
    for rule in ("synth_session_demo", "calibrate", "report"):
        assert rule in r.stdout


def test_missing_rig_folder_is_named(tmp_path):
    folder = _real_session(tmp_path / "s", template_rig=str(tmp_path / "no_such_rig"))
    r = _dry_run(tmp_path, {"sessions": {"real": {"path": str(folder)}}})
    assert r.returncode != 0
    assert "template_rig" in r.out and "no_such_rig" in r.out


def test_missing_character_rig_is_named(tmp_path):
    folder = _real_session(tmp_path / "s")
    r = _dry_run(tmp_path, {"sessions": {"real": {"path": str(folder)}},
                            "characters": {"hero": {"rig": "rigs/hero_missing"}}})
    assert r.returncode != 0
    assert "characters.hero.rig" in r.out and "hero_missing" in r.out


def test_unknown_shape_name_is_named(tmp_path):
    folder = _real_session(tmp_path / "s")
    r = _dry_run(tmp_path, {"sessions": {"real": {"path": str(folder)}}, "shapes": ["jawOpen", "jawWobble"]})
    assert r.returncode != 0
    assert "jawWobble" in r.out and "'shapes'" in r.out


@pytest.mark.parametrize("override,field", [
    ({"image_size": [640]}, "image_size"),
    ({"cameras": ["a", "a"]}, "cameras"),
    ({"board": {"type": "charuco", "squares_x": 7, "squares_y": 5}}, "board"),
    ({"rom": [{"name": "s0", "frames": [5, 3]}]}, "rom.0"),
    ({"colour": "blue"}, "top level"),
    ({"dots": "unpainted"}, "dots"),
])
def test_malformed_session_yaml_names_file_and_field(tmp_path, override, field):
    folder = _real_session(tmp_path / "s", **override)
    r = _dry_run(tmp_path, {"sessions": {"real": {"path": str(folder)}}})
    assert r.returncode != 0
    assert "session.yaml" in r.out and field in r.out, r.out[-2000:]


def test_malformed_config_is_rejected(tmp_path):
    r = _dry_run(tmp_path, {"sessions": {"demo": {"path": "x", "synthetic": {"n_cameras": 1}}}})
    assert r.returncode != 0 and "n_cameras" in r.out


def test_run_sessions_selects_and_names_unknown(tmp_path):
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    cfg["sessions"]["real"] = {"path": str(_real_session(tmp_path / "s"))}
    cfg["run_sessions"] = ["demo"]
    r = _dry_run(tmp_path, cfg)
    assert r.returncode == 0, r.out[-3000:]
    assert "results/demo/report.html" in r.out and "results/real/" not in r.out
    cfg["run_sessions"] = ["demo", "nosuch"]
    r = _dry_run(tmp_path, cfg)
    assert r.returncode != 0
    assert "run_sessions" in r.out and "nosuch" in r.out


@pytest.mark.parametrize("synthetic,key,fix", [
    ({"appearance": "realstic"}, "appearance", "did you mean 'realistic'"),
    ({"dots": "no"}, "dots", "use one of: stencil, none"),
    ({"lights": "sun"}, "lights", "use one of: single, studio"),
    ({"dot_placement_sd_mm": -1.0}, "dot_placement_sd_mm", "give dot_placement_sd_mm >= 0"),
    ({"camera": {"f_number": 0}}, "camera.f_number", "fix:"),
    ({"camera": {"f_numbr": 8}}, "camera.f_numbr", "did you mean 'f_number'"),
    ({"performance": {"marker_placement_sd_mm": -2.0}}, "performance.marker_placement_sd_mm", ">= 0"),
    ({"distortion_k3": [0.1, -0.1]}, "distortion_k3", "lo <= hi"),
    ({"camera": {"exposure_sd": -0.1}}, "camera.exposure_sd", "matched cameras"),
])
def test_bad_realism_keys_fail_at_dag_start_with_the_key_and_the_fix(tmp_path, synthetic, key, fix):
    r = _dry_run(tmp_path, {"sessions": {"s": {"path": str(tmp_path / "s"), "synthetic": synthetic}},
                            "run_sessions": ["s"]})
    assert r.returncode != 0
    assert key in r.out and fix in r.out, r.out[-2000:]
    assert not (tmp_path / "s").exists()


def _calibration_only_session(folder: Path) -> Path:
    """A session of calibration images only (no rom, no performances), JPEG, as a technician has it."""
    folder = _real_session(folder, rom=[])
    for cam in ("a", "b"):
        (folder / "calib" / cam).mkdir(parents=True)
        for k in range(3):
            (folder / "calib" / cam / f"{k}.jpg").write_bytes(b"\xff\xd8 not decoded by a dry run \xff\xd9")
    return folder


def test_calibration_only_session_builds_its_dag(tmp_path):
    """Issue 21 finding 2: calibration images only; `--until calibrate` and a full run both plan."""
    folder = _calibration_only_session(tmp_path / "s")
    cfg = {"sessions": {"real": {"path": str(folder)}}}
    r = _dry_run(tmp_path, cfg, "--until", "calibrate")
    assert r.returncode == 0, r.out[-3000:]
    assert "rule calibrate:" in r.stdout and "track_neutral" not in r.out and "calib/a/2.jpg" in r.stdout
    r = _dry_run(tmp_path, cfg)
    assert r.returncode == 0, r.out[-3000:]
    assert "results/real/report.html" in r.stdout and "results/real/calib/cameras.json" in r.stdout
    assert "reconstruct" not in r.stdout and "track" not in r.stdout


def test_a_technicians_config_plans_only_its_sessions(tmp_path):
    """Issue 21 finding 3: config/config.yaml is loaded first, but a --configfile naming its own sessions
    builds only those (no demo session). Snakemake reads config/config.yaml from the working directory:
    a copy there stands for the project's."""
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "config.yaml").write_text((PROJECT_ROOT / "config" / "config.yaml").read_text())
    folder = _real_session(tmp_path / "s")
    for cam in ("a", "b"):
        for sub, names in (("calib", ["0.png", "1.png"]), ("rom/s0", [f"{f:06d}.png" for f in range(4)])):
            (folder / sub / cam).mkdir(parents=True)
            for n in names:
                (folder / sub / cam / n).write_bytes(b"not decoded by a dry run")
    r = _dry_run(tmp_path, {"sessions": {"real": {"path": str(folder)}}})
    assert r.returncode == 0, r.out[-3000:]
    assert "results/real/report.html" in r.stdout and "rule track_neutral:" in r.stdout
    assert "demo" not in r.stdout and "synth_session" not in r.stdout


def test_session_dots_none_is_an_unpainted_face(tmp_path):
    """session.yaml ``dots: none`` (what the generator writes for ``dots: none``) reads as an unpainted face;
    absent, the dots are painted."""
    from rigbuild.session import read_session
    from rigbuild.synth.session import plan_session

    assert read_session(_real_session(tmp_path / "a")).painted_dots
    assert not read_session(_real_session(tmp_path / "b", dots="none")).painted_dots
    plan = plan_session("u", {"dots": "none", "dot_stencil_mm": 16.0})
    assert plan["dots"] == "none" and "dot_stencil_mm" not in plan
    assert "dots" not in plan_session("p", {"dot_stencil_mm": 16.0})
