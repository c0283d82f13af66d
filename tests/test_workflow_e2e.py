"""The whole DAG on a tiny synthetic session, as a user runs it.

One run serves three acceptance checks of the end-to-end issue:

1. **resume**: `snakemake` is interrupted (SIGINT, as Ctrl-C or a scheduler does) while reconstruction
   runs; the next run finishes without redoing finished jobs and without using a half-written file;
2. **cluster**: a job of the finished run, forced again through ``workflow/profiles/local-cluster``
   (snakemake-executor-plugin-cluster-generic with a local submit script), runs as a separate process from
   files alone (the whole DAG that way: tests/test_cluster_slurm.py);
3. **report**: the HTML report renders every section in headless Chromium (skipped when Chromium is absent).
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from dry_run import planned_jobs
from e2e_run import job_env, snakemake_cmd
from rigbuild.io.metrics import flatten_metrics
from rigbuild.paths import PROJECT_ROOT

PROFILES = PROJECT_ROOT / "workflow" / "profiles"


def test_interrupted_run_resumes_without_redoing_finished_jobs(e2e_run):
    assert e2e_run["interrupted"], e2e_run["run1_log"][-3000:]
    assert e2e_run["locks"] == []  # a graceful stop leaves no stale lock
    r2 = e2e_run["run2"]
    assert r2.returncode == 0, (r2.stdout + r2.stderr)[-5000:]
    calib = e2e_run["results"] / "calib"
    for p, mtime in e2e_run["first_calib"].items():
        assert p.stat().st_mtime_ns == mtime, f"{p.name} was redone"
    assert "rule calibrate" not in r2.stdout + r2.stderr and "synth_session_e2e" not in r2.stdout + r2.stderr
    assert (calib / "cameras.json").exists()


def test_every_output_is_complete(e2e_run):
    """No half-written file: every npz/json/png under results/ loads."""
    import cv2

    n = 0
    for p in e2e_run["results"].rglob("*"):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix == ".npz":
            with np.load(p) as z:
                _ = [z[k] for k in z.files]
        elif p.suffix == ".json":
            json.loads(p.read_text())
        elif p.suffix == ".png":
            assert cv2.imread(str(p)) is not None, p
        n += 1
    assert n > 20


def test_local_cluster_profile_runs_a_job_as_its_own_process(e2e_run, tmp_path):
    """One job (eval_calibration) of a copy of the finished run, forced again through the local-cluster profile."""
    from e2e_run import SUBMIT

    work = tmp_path / "e2e"
    shutil.copytree(e2e_run["tmp"], work, ignore=shutil.ignore_patterns("logs", "locks", "incomplete"))
    r = subprocess.run(snakemake_cmd(work, "--profile", str(PROFILES / "local-cluster"), "--cluster-generic-submit-cmd",
                                     SUBMIT, "--forcerun", "eval_calibration", "--until", "eval_calibration"),
                       capture_output=True, text=True, env=job_env(), cwd=work, timeout=600)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-3000:]
    outs = list((work / "logs" / "cluster").glob("*eval_calibration*.out"))
    assert "Submitted job" in log and len(outs) == 1, log[-3000:]
    assert "Finished job" in outs[0].read_text() or "Finished jobid" in outs[0].read_text()


def test_every_file_written_is_a_declared_output(e2e_run):
    """No job writes a file its rule does not declare: every file under results/ is an output listed by
    `snakemake --summary`, a file inside a declared directory output, or a rule's benchmark record."""
    tmp = e2e_run["tmp"]
    r = subprocess.run(snakemake_cmd(tmp, "--summary"), capture_output=True, text=True, env=job_env(), cwd=tmp, timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    declared = {line.split("\t")[0] for line in r.stdout.splitlines()[1:] if line.strip()}
    dirs = [d for d in declared if (tmp / d).is_dir()]
    undeclared = []
    for p in (tmp / "results").rglob("*"):
        rel = str(p.relative_to(tmp))
        if p.is_file() and rel not in declared and not any(rel.startswith(d + "/") for d in dirs) \
                and "/benchmarks/" not in rel:
            undeclared.append(rel)
    assert len(declared) > 50 and not undeclared, undeclared[:20]


#: loose per-stage bounds on the tiny session (the demo's realistic capture, 2 x 5 ROM frames, 12 poses): far
#: from the goals (rigbuild/report/thresholds.py), but a broken stage (garbage cameras, surfaces, tracks, rig or
#: weights) lands outside them. That session gave rms 0.10 px, centre 0.65 mm, median 0.46 mm, completeness 0.80,
#: tracking 2.04 / 4.25 mm (mean / p95, whole face mask; the head moves 10 mm and 8 degrees), residual reduction
#: 0.31, correlations 0.72 (ribera_fit) and 0.69 (seol), weight MAE 0.21 / 0.28.
STAGE_BOUNDS = {
    "calibration.rms_px": ("<", 0.5),
    "calibration.center_error_mm": ("<", 2.0),
    "reconstruction.median_error_mm": ("<", 1.0),
    "reconstruction.completeness": (">", 0.6),
    "tracking.mean_error_mm": ("<", 4.0),
    "tracking.p95_error_mm": ("<", 8.0),
    "tracking.visible_mean_error_mm": ("<", 4.0),
    "personalization.residual_reduction": (">", 0.0),
    "personalization.residual_reduction_weighted": (">", 0.0),
    "retarget.ribera_fit.template.mean_correlation": (">", 0.5),
    "retarget.ribera_fit.template.weight_mae": ("<", 0.5),
    "retarget.ribera_fit_template_rig.template.mean_correlation": (">", 0.5),
    "retarget.seol.template.mean_correlation": (">", 0.5),
    "retarget.seol.template.weight_mae": ("<", 0.5),
    "retarget.actor_rig_weights.mean_correlation": (">", 0.5),
    "retarget.semantic_actor_rig.template.mean_correlation": (">", 0.5),
    # the take's markers on the tracked neutral: the demo measured 0.82 mm (its marker-set vertices 2.68 mm)
    "retarget.take_markers.marker_map_skin_error_mm": ("<", 2.0),
}


def out_of_bounds(flat: dict) -> list[str]:
    """The :data:`STAGE_BOUNDS` keys that ``flat`` (flat metrics) lacks or holds outside their bound."""
    bad = []
    for key, (op, limit) in STAGE_BOUNDS.items():
        v = flat.get(key)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and (v < limit if op == "<" else v > limit)
        if not ok:
            bad.append(f"{key} = {v} (want {op} {limit})")
    return bad


def test_metrics_hold_every_stage(e2e_run):
    flat = flatten_metrics(json.loads((e2e_run["results"] / "metrics.json").read_text()))
    for key in ("calibration.rms_px", "calibration.center_error_mm", "reconstruction.median_error_mm",
                "reconstruction.completeness", "tracking.mean_error_mm", "tracking.visible_mean_error_mm",
                "personalization.residual_reduction", "personalization.residual_reduction_weighted",
                "retarget.seol.template.mean_correlation", "retarget.ribera.template.weight_mae",
                "retarget.ribera_paper.template.mean_correlation",
                "retarget.rbf_baseline.template.mean_correlation", "retarget.seol.template.velocity_error",
                "retarget.actor_rig_weights.mean_correlation", "retarget.actor_rig_weights.marker_map_error_mm",
                "retarget.actor_rig_weights.unrefined_mean_correlation",
                "retarget.template_rig_weights.mean_correlation",
                "retarget.semantic_actor_rig.template.mean_correlation"):
        assert key in flat and flat[key] is not None, key
    assert not any(k.startswith("tracking.mask_") or "_unweighted" in k or "ribera_faithful" in k for k in flat)


def test_every_stage_is_within_loose_bounds(e2e_run):
    """A broken stage fails here, not only a missing key: each stage's headline numbers within loose bounds."""
    flat = flatten_metrics(json.loads((e2e_run["results"] / "metrics.json").read_text()))
    assert flat["personalization.objective_monotone"] is True
    bad = out_of_bounds(flat)
    assert not bad, "; ".join(bad)


def test_a_new_personalized_rig_reruns_what_reads_it_and_only_that(e2e_run):
    """Re-running the personalization (``--forcerun personalize``, as a TD does after changing its parameters or
    its template) re-plans the jobs that read the personalized rig (the actor-rig solve, the semantic transfer,
    the Ribera and Seol actor-rig variants, their evaluation, metrics and report) and no other retargeting job:
    the template-rig solve and every other Ribera and Seol method stay done. (Touching rig.npz by hand re-plans
    nothing in Snakemake 9: a rule's output is judged by whether its job reruns, not by its mtime.)"""
    tmp = e2e_run["tmp"]
    r = subprocess.run(snakemake_cmd(tmp, "-n", "--forcerun", "personalize"), capture_output=True, text=True, env=job_env(),
                       cwd=tmp, timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    jobs = planned_jobs(r.stdout + r.stderr)
    rules = {rule for rule, _ in jobs}
    assert {"actor_rig_weights", "retarget_semantic", "eval_actor_rig", "metrics", "report"} <= rules, rules
    assert "personalize" in rules and not rules & {"track_sequence", "calibrate", "character_rig"}, rules
    for rule, wc in jobs:
        if rule in ("actor_rig_weights", "eval_actor_rig"):
            assert wc.get("source") == "actor_rig", (rule, wc)
        if rule in ("retarget_ribera", "retarget_seol", "eval_retarget"):
            assert wc.get("method", "").endswith("_actor_rig"), (rule, wc)


def test_report_renders_every_section_in_chromium(e2e_run, tmp_path):
    html = e2e_run["results"] / "report.html"
    text = html.read_text()
    for section in ("calibration", "reconstruction", "tracking", "personalization", "retargeting", "timings"):
        assert f'id="{section}"' in text
    assert "data:image/jpeg;base64," in text and "src=\"http" not in text  # self-contained
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("Chromium is not installed (apt-get install chromium); the HTML checks above ran")
    shot = tmp_path / "report.png"
    dom = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", html.as_uri()],
                         capture_output=True, text=True, timeout=120)
    for section in ("Calibration", "Reconstruction", "Tracking", "Personalization", "Retargeting", "Timings"):
        assert f">{section}" in dom.stdout
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={shot}", "--window-size=1280,4000", html.as_uri()],
                   capture_output=True, timeout=120)
    import cv2

    img = cv2.imread(str(shot))
    assert img is not None and img.shape[1] == 1280
    assert img.std() > 20  # not a blank page: text, tables and embedded pictures rendered
