"""Actor weights from a rig at the markers (issue 26, :mod:`rigbuild.retarget.actor_rig`) on the ICT tiers' takes.

For each tier (config/ict-dev.yaml: the development actor, parameters tuned here; config/ict.yaml and
config/ict-b.yaml: acceptance actors, never tuned on; the demo for reference) the tier's performance is
generated without images (:func:`rigbuild.synth.session.generate_mocap_only`: the same bytes the tier's session
holds: 30 s at 60 fps, markers placed by hand 2 mm along the skin, occlusion gaps, 0.3 mm noise, head motion),
and the markers are placed on, and the weights solved from:

- ``actor``: the actor's true rig (ground_truth/actor_rig.npz): what a perfect personalization would give, the
  ceiling of the ``actor_rig`` path;
- ``template``: the template rig (no personalization): the ``template_rig`` baseline.

The personalized rig itself needs the whole image pipeline on the tier (calibrate, reconstruct, track,
personalize: hours here); its numbers come from a DAG run (``retarget.actor_rig_weights.*``).
Columns: marker-map error (position on the rig's neutral after a face-region rigid alignment, over every marker
and over the markers seen in a placing frame, and along the actor's skin, mm), weight correlation / MAE against the true weights (:mod:`rigbuild.eval.retarget`), and the
solve's speed (frames per second of the batched solve, after the map).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_actor_rig.py [--tune] [--tiers ict_dev,ict]

``--tune`` sweeps lambda_l1 and the marker low-pass on the development actor only. Writes
benchmarks/out/actor_rig.json (from a run of every tier).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import CACHE, cached_session, print_table, write_result  # noqa: E402

from rigbuild.eval.retarget import marker_map_errors, retarget_metrics  # noqa: E402
from rigbuild.io.markers import read_markers  # noqa: E402
from rigbuild.io.rigs import read_rig_npz  # noqa: E402
from rigbuild.paths import PROJECT_ROOT  # noqa: E402
from rigbuild.retarget.actor_rig import (fit_marker_map, marker_map_for_take, sample_rig_at_markers,  # noqa: E402
                                         solve_actor_weights)
from rigbuild.retarget.common import lowpass_markers  # noqa: E402
from rigbuild.retarget.params import ActorRigParams, actor_rig_from_config  # noqa: E402
from rigbuild.synth.session import generate_mocap_only  # noqa: E402

TIERS = {"ict_dev": "config/ict-dev.yaml", "ict": "config/ict.yaml", "ict_b": "config/ict-b.yaml",
         "demo": "config/config.yaml"}


def tier_session(name: str) -> Path:
    """The tier's markers-only session (cached by the config's synthetic block and the generator's sources)."""
    synthetic = yaml.safe_load((PROJECT_ROOT / TIERS[name]).read_text())["sessions"][name]["synthetic"]
    return cached_session(CACHE / name, synthetic, lambda out: generate_mocap_only(out, name, synthetic))


def run(session: Path, which: str, p: ActorRigParams) -> dict:
    """Map + solve one tier's first performance from the ``actor`` or ``template`` rig; its numbers."""
    gt = session / "ground_truth"
    actor = read_rig_npz(gt / "actor_rig.npz")
    rig = actor if which == "actor" else read_rig_npz(gt / "template_rig.npz")
    with np.load(gt / "performances" / "perf00.npz") as z:
        truth = {k: z[k] for k in z.files}
    take = read_markers(session / "performances" / "perf00.c3d")
    P = take.markers if p.marker_lowpass_hz is None else lowpass_markers(take.markers, take.fps, p.marker_lowpass_hz)
    t0 = time.perf_counter()
    m = fit_marker_map(rig.neutral, rig.deltas, rig.faces, P, take.names, marker_map_for_take(rig, take.names),
                       n_frames=p.map_frames, iterations=p.map_iterations, lambda_l1=p.lambda_l1, bounds=p.bounds,
                       observable_mm=p.observable_mm)
    t1 = time.perf_counter()
    b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, m)
    t2 = time.perf_counter()
    sol = solve_actor_weights(b0, D, P, lambda_t=p.temporal_weight(take.fps), lambda_l1=p.lambda_l1,
                              lambda_s=p.lambda_s, bounds=p.bounds, sweeps=p.sweeps, tol=p.tol,
                              observable_mm=p.observable_mm)
    t3 = time.perf_counter()
    names = [str(s) for s in truth["shape_names"]]
    sub = actor.subset(names)
    score = retarget_metrics(sol.weights, rig.shape_names, truth["weights"].astype(np.float64), names,
                             sub.deltas[:, sub.marker_vertices])
    pos, skin = marker_map_errors(m.to_json(), actor, truth, rig)
    F = sol.weights.shape[0]
    return {"frames": F, "markers": len(m.names), "map_s": t1 - t0, "solve_s": t3 - t2, "frames_per_s": F / (t3 - t2),
            "sweeps": sol.sweeps, "converged": sol.converged, "map_error_mm": float(pos.mean()),
            "map_p95_mm": float(np.percentile(pos, 95)), "map_skin_error_mm": float(skin.mean()),
            "map_placed_error_mm": float(pos[m.placed].mean()), "unplaced": int((~m.placed).sum()),
            "residual_mm": float(np.nanmean(sol.residual_mm)), "correlation": score["mean_correlation"],
            "weight_mae": score["weight_mae"]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tune", action="store_true", help="sweep lambda_l1 and the low-pass on ict_dev")
    ap.add_argument("--tiers", default=",".join(TIERS))
    args = ap.parse_args()
    tiers = args.tiers.split(",")
    p = actor_rig_from_config({})
    rows, tune_rows = [], []
    if args.tune:
        session = tier_session("ict_dev")
        for lp in (None, 8.0, 5.0, 3.0):
            for l1 in (0.0, 0.25, 0.5, 1.0, 2.0):
                q = actor_rig_from_config({"lambda_l1": l1, "marker_lowpass_hz": lp})
                r = run(session, "actor", q)
                tune_rows.append({"tier": "ict_dev", "rig": "actor", "lambda_l1": l1, "lowpass_hz": lp, **r})
        print_table(tune_rows, ["lambda_l1", "lowpass_hz", "correlation", "weight_mae", "map_error_mm", "residual_mm"])
    for tier in tiers:
        session = tier_session(tier)
        for which in ("actor", "template"):
            rows.append({"tier": tier, "rig": which, **run(session, which, p)})
    cols = ["tier", "rig", "frames", "map_error_mm", "map_placed_error_mm", "unplaced", "map_skin_error_mm", "correlation", "weight_mae", "residual_mm",
            "frames_per_s", "sweeps", "map_s"]
    print_table(rows, cols)
    if set(tiers) == set(TIERS):
        write_result("actor_rig", {"params": vars(p), "rows": rows, "tune": tune_rows,
                                   "goals": {"correlation": 0.95, "weight_mae": 0.05, "map_error_mm": 0.5,
                                             "frames_per_s": 1000}})


if __name__ == "__main__":
    main()
