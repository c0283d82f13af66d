"""Snakemake entry point: marker-space retargeting after Ribera et al. 2017 of one performance onto one
character with one method (ribera | ribera_activation | ribera_fit | rbf | deformation | parallel).

input: performance (.c3d/.npz markers), training (list of tracked ROM marker .npz: ``markers`` F x M x 3 mm,
``marker_names``), rig (character .npz with its marker map), optional parallel_rig (the actor's personalized
rig .npz, for method ``parallel``).
output: weights (.csv), weights_json, gltf, preview (.png), metrics (.json).
params: ribera (dict, see PARAMS), method, character, performance, neutral_frames (list, per training
sequence), metrics_path.
"""


import logging

import numpy as np

from rigbuild.errors import InputError
from rigbuild.eval.retarget import PRIMARY_RIBERA_METHOD, metric_prefixes
from rigbuild.io.atomic import write_json
from rigbuild.io.gltf_anim import write_gltf_animation
from rigbuild.io.markers import read_markers
from rigbuild.io.metrics import merge_metrics
from rigbuild.io.rigs import read_rig_npz
from rigbuild.logs import run_logged
from rigbuild.retarget.common import write_weight_curves_csv, write_weight_curves_json
from rigbuild.retarget.preview import write_preview
from rigbuild.retarget.ribera import METHODS, RetargetParams, TransferParams
from rigbuild.retarget.run import make_training_set, retarget_performance

log = logging.getLogger("rigbuild.retarget.ribera")

#: config params.retarget.ribera keys and defaults (paper values; lambda_cm is the paper's lambda for cm)
PARAMS = {
    "alpha": 0.01,            # E_Mesh weight (eq. 4)
    "beta": 0.1,              # E_CEG weight (eq. 4)
    "r": 15.0,                # contrast steepness (eq. 7)
    "ceg_reference": "character",
    "guess": "rbf",           # g_k of E_Mesh for ribera / ribera_activation: rbf (sec. 4.4) | deformation
    "fit_guess": "deformation",  # g_k of E_Mesh for ribera_fit
    "fit_alpha": 0.3,         # E_Mesh weight of the ribera_fit match
    "fit_lambda_cm": 0.2,     # E_Sparse weight of the training-frame activations in ribera_fit (cm)
    "rigid": "joint",         # residual head motion fitted jointly with the weights | fixed
    "mu": 0.3,                # E_Prior weight (eq. 16)
    "lambda_cm": 0.6,         # E_Sparse weight for markers in cm (x100 internally for mm)
    "bounds": [0.0, 1.0],     # weight bounds, or null
    "allow_empty_frames": True,
    "preview_frames": 4,
    "primary": PRIMARY_RIBERA_METHOD,  # the variant also reported as retarget.ribera.* (issue 7's keys)
    "marker_lowpass_hz": None,  # zero-phase low-pass of the take's markers (-3 dB, Hz) before solving
}


def main(snakemake) -> None:
    cfg = {**PARAMS, **dict(snakemake.params.get("ribera", None) or {})}
    unknown = sorted(set(cfg) - set(PARAMS))
    if unknown:
        raise InputError(f"unknown params.retarget.ribera keys {unknown}", path="config", fix=f"use {sorted(PARAMS)}")
    method = str(snakemake.params.method)
    if method not in METHODS:
        raise InputError(f"unknown method '{method}'", path="config", fix=f"use one of {METHODS}")
    take = read_markers(snakemake.input.performance)
    training_files = list(snakemake.input.training)
    seqs, names = [], []
    for p in training_files:
        t = read_markers(p)
        seqs.append(t.markers)
        names.append(t.names)
    neutral_frames = snakemake.params.get("neutral_frames", None) or [0]
    training = make_training_set(seqs, names, neutral_frames, training_files)
    rig = read_rig_npz(snakemake.input.rig)
    if rig.marker_vertices.size == 0:
        raise InputError(f"character '{rig.name}' has no marker map", path=snakemake.input.rig,
                         fix="build the character with the session's marker set")
    actor_dp = None
    if method == "parallel":
        if "parallel_rig" not in snakemake.input.keys():
            raise InputError("method 'parallel' needs input 'parallel_rig' (the actor's personalized rig)")
        prig = read_rig_npz(snakemake.input.parallel_rig).subset(rig.shape_names)
        from rigbuild.retarget.common import map_markers_to_vertices

        vids = map_markers_to_vertices(training.names, prig.marker_names, prig.marker_vertices, "personalized rig",
                                       snakemake.input.parallel_rig)
        actor_dp = prig.deltas[:, vids]
    bounds = None if cfg["bounds"] is None else tuple(cfg["bounds"])
    tp = TransferParams(alpha=float(cfg["alpha"]), beta=float(cfg["beta"]), r=float(cfg["r"]),
                        ceg_reference=str(cfg["ceg_reference"]),
                        guess=str(cfg["fit_guess"] if method == "ribera_fit" else cfg["guess"]),
                        fit_alpha=float(cfg["fit_alpha"]), fit_lambda_cm=float(cfg["fit_lambda_cm"]))
    rp = RetargetParams(mu=float(cfg["mu"]), lambda_cm=float(cfg["lambda_cm"]), bounds=bounds, rigid=str(cfg["rigid"]))
    res = retarget_performance(training, take.markers, take.names, rig, rig.marker_names, rig.marker_vertices,
                               method, tp, rp, actor_blendshapes=actor_dp,
                               allow_empty_frames=bool(cfg["allow_empty_frames"]),
                               performance_path=snakemake.input.performance, map_path=snakemake.input.rig,
                               workers=int(snakemake.threads),
                               marker_lowpass_hz=None if cfg["marker_lowpass_hz"] is None else float(cfg["marker_lowpass_hz"]),
                               fps=take.fps)
    out = snakemake.output
    fps = take.fps
    meta = {"method": method, "character": rig.name, "params": cfg}
    write_weight_curves_csv(out.weights, res.weights, res.shape_names, fps)
    write_weight_curves_json(out.weights_json, res.weights, res.shape_names, fps, meta=meta)
    write_gltf_animation(out.gltf, rig, res.weights, fps)
    F = res.weights.shape[0]
    activity = np.abs(res.weights).sum(1)
    n_prev = max(1, int(cfg["preview_frames"]))
    frames = sorted(set(np.argsort(-activity)[: n_prev].tolist()))
    write_preview(out.preview, res.stabilized, training.neutral, rig, res.weights, frames, fps,
                  title=f"{snakemake.params.performance} -> {rig.name} ({method})")
    char = snakemake.params.character
    jitter = float(np.sqrt(np.mean(np.diff(res.weights, 2, axis=0) ** 2))) if F > 2 else 0.0
    values = {"build_s": res.timings["build_s"], "retarget_s": res.timings["retarget_s"],
              "frames_per_s": F / max(res.timings["retarget_s"], 1e-9), "n_frames": F,
              "n_markers": len(training.names), "empty_frames": int(res.empty_frames.size),
              "weight_min": float(res.weights.min()), "weight_max": float(res.weights.max()),
              "second_difference_rms": jitter}
    if res.model.transfer is not None:
        values["n_keys"] = int(res.model.transfer.keys.size)
    write_json(out.metrics, {"character": char, "performance": snakemake.params.performance, "method": method,
                             **values})
    merge_metrics(snakemake.params.metrics_path, "retarget",
                  {f"{prefix}.{char}.{k}": v for prefix in metric_prefixes(method, str(cfg["primary"]))
                   for k, v in values.items()})
    log.info("%s %s -> %s: %d frames, build %.2f s, %.0f frames/s", method, snakemake.params.performance, char, F,
             values["build_s"], values["frames_per_s"])


run_logged(snakemake, main)  # noqa: F821
