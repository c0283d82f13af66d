"""Snakemake entry point: spacetime expression cloning (Seol et al. 2012) of one performance onto one
character, with the sec. 7 per-frame baselines and the fig. 11 velocity-error plot.

input: performance (.c3d/.npz markers), rig (character .npz), optional neutral (one or more tracked ROM
marker .npz files; row ``neutral_frames[i]`` of file i is a neutral pose; the actor's neutral is their
rigidly aligned mean, as for the Ribera method; default: the performance's first frame).
output: weights (.csv), weights_json, gltf, plot (.png), metrics (.json), system (.npz for edits).
params: seol (dict, see PARAMS below), character, performance, metrics_path, neutral_frames (list).
"""


import logging
import time

import numpy as np

from rigbuild.errors import InputError
from rigbuild.eval.seol import flat_metric_keys
from rigbuild.io.atomic import write_json
from rigbuild.io.markers import read_markers
from rigbuild.io.metrics import merge_metrics
from rigbuild.io.rigs import read_rig_npz
from rigbuild.logs import run_logged
from rigbuild.retarget.common import average_neutral, reorder_markers, write_weight_curves_csv, write_weight_curves_json
from rigbuild.retarget.seol import (
    retarget_seol,
    sobolev_beta,
    sobolev_beta_from_corner_hz,
    sparse_combination_weights,
)
from rigbuild.io.gltf_anim import write_gltf_animation
from rigbuild.retarget.seol_outputs import plot_velocity_error

log = logging.getLogger("rigbuild.retarget.seol")

#: config params.retarget.seol keys and defaults
PARAMS = {
    "alpha": 0.01,                 # prior weight of eq. (4)
    "alpha_perframe": 0.5,         # "Prior PF" baseline
    "weight_range": [-0.5, 1.5],   # "Range PF" baseline
    "boundary_frames": [0, -1],
    "boundary_values": "neutral",  # neutral | perframe
    "pins": {},                    # {frame: {shape: value}}
    "rigid_weights": "rigidity",   # rigidity | uniform
    "head_refine_iterations": 3,
    "sobolev": None,               # {"regions": {regex: beta}, "frames": [..] or null}
    "sobolev_corner_hz": None,     # uniform Sobolev term on every marker, beta = (2 pi f_c / fps)^2
    "gaps": "mask",                # mask (gaps left out of the energy) | interpolate
    "prior_corner_hz": None,       # prior strength as a corner frequency (Hz); overrides alpha
    "prior_combinations": 0,       # extra sparse-combination training frames for the PCA prior
    "prior_combination_density": 0.15,
    # scale-proportion matching (sec. 3.2; rigbuild.retarget.proportion): rbf (the paper) |
    # deformation (target blendshapes deformation-transferred onto the RBF-warped target mesh) |
    # jacobian | local_affine | affine | none
    "scale_match": "rbf",
    "scale_match_kernel": "r",     # the RBF's phi: r (the paper) | r3 | tps
    "marker_lowpass_hz": None,     # zero-phase low-pass of the take's markers (-3 dB, Hz) before solving
    "weight_bounds": None,         # [lo, hi]: the spacetime solution kept in the rig's weight range
    "sparsity": 0.0,               # L1 weight (mm^2 per unit weight); needs weight_bounds from 0
}


def main(snakemake) -> None:
    cfg = {**PARAMS, **dict(snakemake.params.get("seol", None) or {})}
    unknown = sorted(set(cfg) - set(PARAMS))
    if unknown:
        raise InputError(f"unknown params.retarget.seol keys {unknown}", path="config", fix=f"use {sorted(PARAMS)}")
    t0 = time.perf_counter()
    take = read_markers(snakemake.input.performance)
    rig = read_rig_npz(snakemake.input.rig)
    names = [n for n in rig.marker_names if n in set(take.names)]
    if len(names) < 4:
        raise InputError(f"only {len(names)} markers of the take are on character '{rig.name}'",
                         path=snakemake.input.performance, fix="use a character marker map with the take's marker names")
    X = reorder_markers(take.markers, take.names, names, path=snakemake.input.performance)
    neutral = None
    if "neutral" in snakemake.input.keys():
        files = [snakemake.input.neutral] if isinstance(snakemake.input.neutral, str) else list(snakemake.input.neutral)
        frames = list(snakemake.params.get("neutral_frames", None) or [0] * len(files))
        if len(frames) != len(files):
            raise InputError(f"{len(files)} neutral marker files but {len(frames)} neutral frames", path="rules",
                             fix="give one neutral frame per ROM marker file")
        rows = []
        for path, frame in zip(files, frames):
            rom = read_markers(path)
            if not 0 <= int(frame) < rom.markers.shape[0]:
                raise InputError(f"neutral frame {frame} outside the {rom.markers.shape[0]} frames", path=path)
            rows.append(reorder_markers(rom.markers, rom.names, names, what="neutral sequence", path=path)[int(frame)])
        neutral = average_neutral(np.stack(rows))
    beta = None
    if cfg["sobolev"]:
        sob = cfg["sobolev"]
        beta = sobolev_beta(names, sob.get("regions", {}), X.shape[0] if sob.get("frames") else None, sob.get("frames"))
    if cfg["sobolev_corner_hz"] is not None:
        uniform = sobolev_beta_from_corner_hz(len(names), float(cfg["sobolev_corner_hz"]), float(take.fps))
        beta = uniform if beta is None else np.maximum(beta, uniform)
    rw = None if cfg["rigid_weights"] == "uniform" else cfg["rigid_weights"]
    pins = {int(f): v for f, v in (cfg["pins"] or {}).items()}
    n_comb = int(cfg["prior_combinations"] or 0)
    training = (sparse_combination_weights(rig.n_shapes, n_comb, float(cfg["prior_combination_density"]))
                if n_comb > 0 else None)
    corner = cfg["prior_corner_hz"]
    res = retarget_seol(X, rig, marker_names=names, source_neutral=neutral, alpha=float(cfg["alpha"]),
                        gaps=str(cfg["gaps"]), prior_training=training,
                        prior_corner_hz=None if corner is None else float(corner), fps=float(take.fps),
                        boundary_frames=cfg["boundary_frames"], pins=pins, boundary_values=cfg["boundary_values"],
                        rigid_weights=rw, head_refine_iterations=int(cfg["head_refine_iterations"]), beta=beta,
                        alpha_perframe=float(cfg["alpha_perframe"]), weight_range=tuple(cfg["weight_range"]),
                        scale_match=str(cfg["scale_match"]), scale_match_kernel=str(cfg["scale_match_kernel"]),
                        marker_lowpass_hz=None if cfg["marker_lowpass_hz"] is None else float(cfg["marker_lowpass_hz"]),
                        weight_bounds=None if cfg["weight_bounds"] is None else tuple(cfg["weight_bounds"]),
                        sparsity=float(cfg["sparsity"] or 0.0))
    seconds = time.perf_counter() - t0
    fps = take.fps
    out = snakemake.output
    write_weight_curves_csv(out.weights, res.weights, res.shape_names, fps)
    write_weight_curves_json(out.weights_json, res.weights, res.shape_names, fps,
                             meta={"method": "seol2012", "alpha": res.alpha, "character": rig.name,
                                   "scale_match": cfg["scale_match"]})
    # head motion and pivot are in mm: write the character in mm too
    write_gltf_animation(out.gltf, rig if rig.units == "mm" else rig.to_units("mm"), res.weights, fps,
                         res.head_rotation, res.head_translation, pivot=res.target_pivot)
    plot_velocity_error(out.plot, res.velocity_error, fps, title=f"{snakemake.params.performance} -> {rig.name}")
    res.system.save(out.system)
    char = snakemake.params.character
    values = {"seconds": seconds, "n_frames": int(X.shape[0]), "n_markers": len(names), "alpha": res.alpha}
    per_method = {}
    for method, curve in res.velocity_error.items():
        W = res.weights if method == "spacetime" else res.baselines[method]
        per_method[method] = {"velocity_error": float(curve.sum()), "weight_min": float(W.min()),
                              "weight_max": float(W.max())}
    write_json(out.metrics, {"character": char, "performance": snakemake.params.performance, "params": cfg,
                             **values, "methods": per_method})
    flat = {f"seol.{char}.{k}": v for k, v in values.items()}
    flat.update(flat_metric_keys(per_method, char))
    merge_metrics(snakemake.params.metrics_path, "retarget", flat)
    log.info("seol %s -> %s: %d frames in %.2f s, velocity error %.1f (Range PF %.1f, Prior PF %.1f)",
             snakemake.params.performance, char, X.shape[0], seconds, per_method["spacetime"]["velocity_error"],
             per_method["perframe_range"]["velocity_error"], per_method["perframe_prior"]["velocity_error"])


run_logged(snakemake, main)  # noqa: F821
