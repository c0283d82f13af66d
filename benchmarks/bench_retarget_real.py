"""Retargeting real performances: the four AnimFace takes (41 markers, 60 Hz, Maya ASCII) onto the ICT template.

The actor's training set is all four takes (neutral: the Jaw take's frame 0); each take is then retargeted with
the model. Plausibility numbers per take and over all four (issue 23, :mod:`rigbuild.retarget.plausible`):
frames with an antagonist pair both above 0.3 (goal <= 2 %), mean shapes above 0.1 per frame (goal <= 6),
frames with an eye or brow shape above 0.2 on the Jaw take (goal <= 5 %), RMS second difference of the weight
curves (goal: not worse than the papers' terms alone), and retargeting frames per CPU second (the machine is
shared: CPU time is the fairer number; the Ribera rows include the low-pass and the stabilization).

Variants: ``ribera_fit`` with the pipeline's settings (config/config.yaml ``params.retarget.ribera``) with the
papers' terms only (``plain``) and with the plausibility options (``plausible``,
:mod:`rigbuild.retarget.ribera.plausible`); ``ribera`` as written (the paper's constants), and with the
options (which need weight bounds: [0, 1] added); Seol (config/config.yaml ``params.retarget.seol``) as
configured, with the log sparsity penalty, and with antagonist exclusion too (:data:`SEOL_OPTIONS`).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_retarget_real.py [--variants a,b]

Writes benchmarks/out/retarget_real.json (only from a run of every variant).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, write_result  # noqa: E402

from rigbuild.io.maya_ascii import read_maya_locator_animation  # noqa: E402
from rigbuild.io.rigs import read_ict_rig  # noqa: E402
from rigbuild.paths import PROJECT_ROOT, data_dir, ict_dir  # noqa: E402
from rigbuild.retarget.marker_maps import MARKER_DATA_DIR, read_marker_map  # noqa: E402
from rigbuild.retarget.params import PLAUSIBLE, ribera_from_config  # noqa: E402
from rigbuild.retarget.plausible import plausibility_metrics  # noqa: E402
from rigbuild.retarget.run import apply_model, make_training_set, prepare_model  # noqa: E402

TAKES = ("Jaw", "Eyebrows", "Cheeks", "Nose")
#: regions whose markers do not move in a take (the brief: eyes and brows on the Jaw take)
STILL = {"Jaw": ("eyes", "brows")}
GOALS = {"antagonist_fraction": 0.02, "mean_active": 6.0, "still_fraction": 0.05}
VARIANTS = ("ribera_fit.plain", "ribera_fit.plausible", "ribera.plain", "ribera.plausible", "seol.plain", "seol.log",
            "seol.plausible")
#: the Seol options measured (on top of config/config.yaml's params.retarget.seol): the log sparsity penalty with
#: slope 1 mm^2 per unit weight at 0, and with antagonist exclusion
SEOL_OPTIONS = {"plain": {}, "log": {"sparsity_mode": "log", "sparsity": 1.0},
                "plausible": {"sparsity_mode": "log", "sparsity": 1.0, "antagonists": True}}


def load_takes(folder: Path) -> dict:
    return {n: read_maya_locator_animation(folder / f"{n}MoCap.ma", group="MoCapData") for n in TAKES}


def pipeline_params():
    """``params.retarget.ribera`` of config/config.yaml (the pipeline's settings)."""
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    return ribera_from_config(cfg["params"]["retarget"]["ribera"])


def _row(label: str, name: str, W: np.ndarray, shape_names, frames_per_cpu_s: float, build_s: float) -> dict:
    m = plausibility_metrics(W, shape_names, STILL.get(name, ()))
    return {"variant": label, "take": name, **m, "weight_min": float(W.min()), "weight_max": float(W.max()),
            "outside_01": float(((W < 0) | (W > 1)).mean()), "frames_per_cpu_s": frames_per_cpu_s, "build_s": build_s}


def _pooled(label: str, rows: list[dict], weights: list[np.ndarray], shape_names, build_s: float) -> dict:
    W = np.concatenate(weights)
    m = plausibility_metrics(W, shape_names)
    return {"variant": label, "take": "all", **m, "outside_01": float(((W < 0) | (W > 1)).mean()),
            "still_fraction": rows[0]["still_fraction"], "build_s": build_s,
            "second_difference_rms": float(np.sqrt(np.mean([r["second_difference_rms"] ** 2 for r in rows])))}


def run_seol_variant(label: str, takes: dict, rig, map_names, map_ids) -> list[dict]:
    """Seol with the pipeline's params.retarget.seol (plus :data:`SEOL_OPTIONS`), the Jaw take's frame 0 as the
    source neutral of every take."""
    from rigbuild.retarget.common import reorder_markers
    from rigbuild.retarget.params import seol_from_config
    from rigbuild.retarget.seol import retarget_seol

    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    p = replace(seol_from_config(cfg["params"]["retarget"]["seol"]), **SEOL_OPTIONS[label.split(".")[1]])
    target = rig.with_markers(map_names, map_ids)
    Y = reorder_markers(takes["Jaw"].markers, takes["Jaw"].names, map_names)[0]
    rows, weights = [], []
    for name, take in takes.items():
        X = reorder_markers(take.markers, take.names, map_names)
        c0 = time.process_time()
        res = retarget_seol(X, target, marker_names=map_names, source_neutral=Y, params=p, fps=take.fps,
                            baselines=False)
        rows.append(_row(label, name, res.weights, res.shape_names, X.shape[0] / (time.process_time() - c0), 0.0))
        weights.append(res.weights)
        print(rows[-1], flush=True)
    return rows + [_pooled(label, rows, weights, res.shape_names, 0.0)]


def run_variant(label: str, takes: dict, training, rig, map_names, map_ids, pairs) -> list[dict]:
    method, mode = label.split(".")
    if method == "seol":
        return run_seol_variant(label, takes, rig, map_names, map_ids)
    p = pipeline_params()
    q = p.for_method(method)
    rp = p.retarget_params(method)
    if mode == "plausible":  # the options on top (the paper's variant: with bounds [0, 1], which they need)
        rp = replace(rp, bounds=rp.bounds or (0.0, 1.0), **PLAUSIBLE)
    t0 = time.perf_counter()
    model = prepare_model(training, rig, map_names, map_ids, method, p.transfer_params(method), rp, pairs)
    build_s = time.perf_counter() - t0
    rows, weights = [], []
    for name, take in takes.items():
        c0 = time.process_time()
        res = apply_model(model, training, take.markers, take.names,
                          marker_lowpass_hz=None if q.marker_lowpass_hz is None else float(q.marker_lowpass_hz),
                          fps=take.fps)
        rows.append(_row(label, name, res.weights, res.shape_names,
                         take.markers.shape[0] / (time.process_time() - c0), build_s))
        weights.append(res.weights)
        print(rows[-1], flush=True)
    return rows + [_pooled(label, rows, weights, model.shape_names, build_s)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    folder = data_dir() / "animface-facial-mocap"
    takes = load_takes(folder)
    training = make_training_set([t.markers for t in takes.values()], [t.names for t in takes.values()])
    rig = read_ict_rig(ict_dir())
    map_names, map_ids, pairs = read_marker_map(MARKER_DATA_DIR / "animface_ict.json")
    rows = []
    for v in variants:
        rows += run_variant(v, takes, training, rig, map_names, map_ids, pairs)
    cols = ["variant", "take", "antagonist_fraction", "worst_antagonist_pair", "mean_active", "still_fraction",
            "second_difference_rms", "outside_01", "frames_per_cpu_s", "build_s"]
    print_table(rows, cols)
    if set(variants) == set(VARIANTS):
        write_result("retarget_real", {"rows": rows, "goals": GOALS, "takes": list(TAKES),
                                       "still_regions": {k: list(v) for k, v in STILL.items()},
                                       "settings": "config/config.yaml params.retarget.ribera"})


if __name__ == "__main__":
    main()
