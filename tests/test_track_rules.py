"""The tracking rules: fragments of the session summary, and the ground-truth evaluation rule's declared inputs."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import yaml

from rigbuild.paths import PROJECT_ROOT


def test_track_summary_pools_the_sequence_fragments(tmp_path):
    from rigbuild.io.metrics import gather_metrics, write_metrics_fragment
    from rigbuild.track.stage import run_track_summary

    paths = []
    for name, lost in (("rom00", []), ("rom01", [4, 5])):
        p = tmp_path / name / "track_metrics.json"
        p.parent.mkdir()
        write_metrics_fragment(p, "tracking", {"sequences": {name: {"frames": 6, "lost_frames": len(lost),
                                                                     "seconds_per_frame": 1.5}}})
        paths.append(p)
    frag = run_track_summary(paths, tmp_path / "track_summary.json", tmp_path / "summary_metrics.json")
    assert frag == {"tracking": {"lost_frames": 2, "sequence_count": 2}}
    summary = json.loads((tmp_path / "track_summary.json").read_text())
    assert summary["tracking"] == {"lost_frames": 2, "sequences": 2}
    assert summary["sequences"]["rom01"]["lost_frames"] == 2
    merged = gather_metrics(paths + [tmp_path / "summary_metrics.json"])["tracking"]
    assert merged["lost_frames"] == 2 and merged["sequences"]["rom01"]["lost_frames"] == 2


def test_stage_code_does_not_touch_ground_truth():
    for path in [PROJECT_ROOT / "scripts" / "track.py", *sorted((PROJECT_ROOT / "rigbuild" / "track").glob("*.py"))]:
        text = path.read_text()
        assert not re.search(r"rigbuild\.(eval|synth)|ground_truth", text), path


def test_eval_rule_declares_every_ground_truth_file(tmp_path):
    """Dry run of the demo: rule eval_track reads ground_truth/cameras.json and every ROM sequence's
    ground_truth/rom/<seq>.npz, all declared as inputs."""
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    cfg["sessions"]["demo"]["path"] = str(tmp_path / "demo")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    snakemake = str(Path(sys.executable).with_name("snakemake"))
    r = subprocess.run([snakemake, "-n", "--configfile", str(tmp_path / "config.yaml"), "--directory", str(tmp_path),
                        "--snakefile", str(PROJECT_ROOT / "Snakefile"), "--cores", "1",
                        "results/demo/eval/tracking_metrics.json"],
                       capture_output=True, text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=300)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-3000:]
    block = out[out.index("rule eval_track:"):]
    inputs = block[block.index("input:"):].splitlines()[0]
    gt = str(tmp_path / "demo" / "ground_truth")
    from rigbuild.synth.session import plan_session

    rom = [s["name"] for s in plan_session("demo", cfg["sessions"]["demo"]["synthetic"])["rom"]]
    for rel in ["cameras.json"] + [f"rom/{s}.npz" for s in rom]:
        assert f"{gt}/{rel}" in inputs, rel
    assert inputs.count(gt) == 1 + len(rom)
