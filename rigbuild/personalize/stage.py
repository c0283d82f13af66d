"""The personalization stage: tracked ROM sequences + template rig -> personalized rig and reports.

Called by ``scripts/personalize.py`` (rule ``personalize``); usable without Snakemake (tests).
Reads ``ground_truth/`` only through :mod:`rigbuild.eval.personalization`, and only when present.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.deformation_transfer import deformation_transfer_aligned
from rigbuild.io.atomic import save_npz, write_json
from rigbuild.io.gltf import write_gltf_rig
from rigbuild.io.metrics import merge_metrics
from rigbuild.io.rigs import write_obj_folder_rig, write_rig_npz
from rigbuild.personalize.em import PersonalizeParams, fit_weights_and_rigid, personalize
from rigbuild.personalize.plots import plot_convergence, render_change_heatmap, render_change_overview
from rigbuild.rig import Rig

log = logging.getLogger(__name__)

#: stage options besides the PersonalizeParams fields
STAGE_KEYS = {"held_out_sequences", "neutral_sequence", "neutral_frame", "fit_region", "template_rig",
              "heatmaps"}


def split_params(cfg: Mapping | None) -> tuple[PersonalizeParams, dict]:
    """``config["params"]["personalize"]`` -> (PersonalizeParams, stage options). Unknown keys are an
    InputError naming them."""
    cfg = dict(cfg or {})
    fields = {f.name for f in dataclasses.fields(PersonalizeParams)}
    unknown = sorted(set(cfg) - fields - STAGE_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {unknown} in params.personalize", path="config",
                         fix=f"use: {', '.join(sorted(fields | STAGE_KEYS))}")
    return PersonalizeParams(**{k: v for k, v in cfg.items() if k in fields}), {k: v for k, v in cfg.items() if k in STAGE_KEYS}


def read_tracked_sequence(path: str | os.PathLike, n_vertices: int) -> dict:
    """``results/{session}/track/{sequence}/vertices.npz`` -> dict(vertices (F, V, 3) mm, confidence
    (F, V), frames (F,) or None). InputError when the topology differs from the rig."""
    path = Path(path)
    if not path.exists():
        raise InputError("tracked sequence not found", path=path, fix="run the track stage first")
    with np.load(path, allow_pickle=False) as z:
        if "vertices" not in z:
            raise InputError("tracked sequence lacks key 'vertices'", path=path)
        v = z["vertices"].astype(np.float64)
        conf = z["confidence"].astype(np.float64) if "confidence" in z else np.ones(v.shape[:2])
        frames = z["frames"].astype(np.int64) if "frames" in z else None
    if v.ndim != 3 or v.shape[2] != 3:
        raise InputError(f"'vertices' must be (F, V, 3), got {v.shape}", path=path)
    if v.shape[1] != n_vertices:
        raise InputError(
            f"rig topology differs from the tracked meshes: {v.shape[1]} tracked vertices, the template rig "
            f"has {n_vertices}",
            path=path,
            fix="track with the same template rig (params.personalize.template_rig / session.yaml template_rig)",
        )
    if conf.shape != v.shape[:2]:
        raise InputError(f"'confidence' must be (F, V) = {v.shape[:2]}, got {conf.shape}", path=path)
    return {"vertices": v, "confidence": np.clip(conf, 0.0, None), "frames": frames}


def frame_numbers(sequence: dict) -> np.ndarray:
    """Session frame numbers (F,) of a :func:`read_tracked_sequence` result (0..F-1 when the file has none)."""
    return sequence["frames"] if sequence["frames"] is not None else np.arange(sequence["vertices"].shape[0])


def neutral_frame_mask(data: Mapping[str, dict], names: list[str], neutral_frames: Mapping[str, int] | None
                       ) -> np.ndarray:
    """(N,) bool over the concatenated frames of sequences ``names``: the frame each sequence names as its
    neutral (``neutral_frames[sequence]``, a session frame number; sequences without one have none)."""
    out = []
    for s in names:
        fr = frame_numbers(data[s])
        nf = (neutral_frames or {}).get(s)
        out.append(np.zeros(fr.shape[0], dtype=bool) if nf is None else fr == int(nf))
    return np.concatenate(out) if out else np.zeros(0, dtype=bool)


def run_personalization(
    tracks: Mapping[str, str | os.PathLike],
    template: Rig,
    out_dir: str | os.PathLike,
    cfg: Mapping | None = None,
    metrics_path: str | os.PathLike | None = None,
    session_dir: str | os.PathLike | None = None,
    neutral_frames: Mapping[str, int] | None = None,
    cameras_json: str | os.PathLike | None = None,
    workers: int = 1,
) -> dict:
    """Run the whole stage.

    tracks : sequence name -> vertices.npz (in session order).
    template : the template rig (mm), same topology as the tracked meshes.
    out_dir : results/{session}/personalize.
    cfg : ``config["params"]["personalize"]`` (PersonalizeParams fields + ``held_out_sequences``,
        ``neutral_sequence``, ``neutral_frame``, ``fit_region`` ("face" | "all"), ``heatmaps``).
    metrics_path : results/{session}/metrics.json (merged under ``personalization``).
    cameras_json : the calibrated cameras; with ground truth, the rig is mapped from the calibrated world
        into the ground-truth world (similarity on the camera centres) before it is compared.
    session_dir : the session folder; its ``ground_truth/`` (if any) feeds the GT metrics.
    neutral_frames : sequence -> the session frame number of its neutral pose (SequenceSpec.neutral_frame).
    workers : processes for the initial rig's per-shape deformation transfer (the job's threads).

    Returns the metrics dict.
    """
    params, opts = split_params(cfg)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(tracks)
    held = [s for s in opts.get("held_out_sequences", []) if s in tracks]
    missing = [s for s in opts.get("held_out_sequences", []) if s not in tracks]
    if missing:
        raise InputError(f"held-out sequence(s) {missing} are not ROM sequences of this session", path="config",
                         fix=f"params.personalize.held_out_sequences must name some of: {', '.join(names)}")
    fit_names = [s for s in names if s not in held]
    if not fit_names:
        raise InputError("every ROM sequence is held out; nothing to fit", path="config",
                         fix="hold out fewer sequences in params.personalize.held_out_sequences")
    data = {s: read_tracked_sequence(tracks[s], template.n_vertices) for s in names}

    # the actor's neutral b_0: the neutral frame of the chosen sequence
    nseq = opts.get("neutral_sequence", fit_names[0])
    if nseq not in data:
        raise InputError(f"neutral_sequence '{nseq}' is not a ROM sequence", path="config")
    nframe = opts.get("neutral_frame", (neutral_frames or {}).get(nseq))
    fr = data[nseq]["frames"]
    idx = 0
    if nframe is not None and fr is not None:
        hits = np.flatnonzero(fr == int(nframe))
        idx = int(hits[0]) if hits.size else 0
    b0 = data[nseq]["vertices"][idx]
    log.info("neutral: sequence %s, tracked frame index %d", nseq, idx)

    region = template.face_vertices if opts.get("fit_region", "face") == "face" else None
    # the tracked neutral is in the calibrated cameras' world, the template in its own: the template's shapes are
    # turned with the template placed on b0 before their deformation gradients are transferred
    Dstar = deformation_transfer_aligned(template.neutral, template.deltas, template.faces, b0,
                                         align_vertices=template.face_vertices, workers=workers)
    zero = [template.shape_names[k] for k in range(template.n_shapes) if not np.any(Dstar[k])]
    if zero:
        raise InputError(f"all-zero shape(s) in the template rig: {', '.join(zero)}",
                         fix="remove them from the template (config 'shapes:') or fix the rig files")

    frames = np.concatenate([data[s]["vertices"] for s in fit_names])
    conf = np.concatenate([data[s]["confidence"] for s in fit_names])
    seq_ids = np.concatenate([np.full(data[s]["vertices"].shape[0], i) for i, s in enumerate(fit_names)])
    res = personalize(b0, Dstar, template.faces, frames, conf, seq_ids, params, template.shape_names, region,
                      neutral_mask=neutral_frame_mask(data, fit_names, neutral_frames))
    for m in res.warnings:
        log.warning("%s", m)

    rig = dataclasses.replace(template.copy(), neutral=res.neutral, deltas=res.deltas, name="personalized")
    initial = dataclasses.replace(template.copy(), neutral=b0, deltas=Dstar, name="initial")
    write_rig_npz(out / "rig.npz", rig)
    write_rig_npz(out / "initial_rig.npz", initial)
    write_obj_folder_rig(rig, out / "rig_obj")
    write_gltf_rig(out / "rig.gltf", rig)

    # held-out frames: weights + rigid with the initial and the personalized rig
    ho = {}
    if held:
        hf = np.concatenate([data[s]["vertices"] for s in held])
        hc = np.concatenate([data[s]["confidence"] for s in held])
        hid = np.concatenate([np.full(data[s]["vertices"].shape[0], i) for i, s in enumerate(held)])
        vtx = None if region is None else region
        hc_fit = hc if region is None else np.where(np.isin(np.arange(template.n_vertices), region)[None], hc, 0.0)
        hn = neutral_frame_mask(data, held, neutral_frames)
        ho["initial"] = fit_weights_and_rigid(b0, Dstar, hf, hc_fit, hid, params, vertices=vtx, neutral_mask=hn)
        ho["final"] = fit_weights_and_rigid(res.neutral, res.deltas, hf, hc_fit, hid, params, vertices=vtx,
                                            neutral_mask=hn)

    seq_col = np.concatenate([np.full(data[s]["vertices"].shape[0], s) for s in fit_names])
    frame_col = np.concatenate([frame_numbers(data[s]) for s in fit_names])
    arrays = dict(weights=res.weights.astype(np.float32), rotation=res.rotations.astype(np.float32),
                  translation=res.translations.astype(np.float32), sequence=seq_col, frame=frame_col,
                  kept=res.kept, shape_names=np.asarray(template.shape_names))
    if held:
        arrays.update(heldout_weights=ho["final"]["weights"].astype(np.float32),
                      heldout_rotation=ho["final"]["rotations"].astype(np.float32),
                      heldout_translation=ho["final"]["translations"].astype(np.float32),
                      heldout_sequence=np.concatenate([np.full(data[s]["vertices"].shape[0], s) for s in held]))
    save_npz(out / "weights.npz", **arrays)
    write_json(out / "objective.json", {"objective": res.objective, "timings": res.timings,
                                         "n_free_variables": res.n_free_variables, "warnings": res.warnings,
                                         "params": dataclasses.asdict(params), "fit_sequences": fit_names,
                                         "held_out_sequences": held})
    plot_convergence(res.objective, out / "convergence.png")
    hm = out / "heatmaps"
    hm.mkdir(exist_ok=True)
    render_change_overview(b0, Dstar, res.deltas, template.faces, template.shape_names, hm / "overview.png", region)
    if opts.get("heatmaps", True):
        for k, name in enumerate(template.shape_names):
            render_change_heatmap(b0, Dstar[k], res.deltas[k], template.faces, hm / f"{name}.png", name, region)

    metrics = {
        "residual_initial_mm": res.residual_initial_mm,
        "residual_final_mm": res.residual_final_mm,
        "residual_reduction": 1.0 - res.residual_final_mm / res.residual_initial_mm,
        "residual_initial_unweighted_mm": res.residual_initial_unweighted_mm,
        "residual_final_unweighted_mm": res.residual_final_unweighted_mm,
        "residual_reduction_unweighted": 1.0 - res.residual_final_unweighted_mm / res.residual_initial_unweighted_mm,
        "em_iterations": int(res.objective[-1]["iteration"]),
        "objective_initial": res.objective[0]["total"],
        "objective_final": res.objective[-1]["total"],
        "objective_monotone": bool(np.all(np.diff([o["total"] for o in res.objective]) <= 1e-9 * res.objective[0]["total"])),
        "frames_fitted": int(res.kept.sum()),
        "frames_skipped": int((~res.kept).sum()),
        "free_variables": int(res.n_free_variables),
        "runtime_s": res.timings["total_s"],
        "qp_median_ms": res.timings["qp_median_ms"],
    }
    if held:
        metrics.update(heldout_residual_initial_mm=ho["initial"]["rms_mm"], heldout_residual_final_mm=ho["final"]["rms_mm"],
                       heldout_residual_reduction=1.0 - ho["final"]["rms_mm"] / ho["initial"]["rms_mm"],
                       heldout_residual_initial_unweighted_mm=ho["initial"]["rms_unweighted_mm"],
                       heldout_residual_final_unweighted_mm=ho["final"]["rms_unweighted_mm"],
                       heldout_residual_reduction_unweighted=1.0 - ho["final"]["rms_unweighted_mm"]
                       / ho["initial"]["rms_unweighted_mm"])

    gt_dir = Path(session_dir) / "ground_truth" if session_dir is not None else None
    if gt_dir is not None and (gt_dir / "actor_rig.npz").exists():
        from rigbuild.eval.personalization import ground_truth_metrics

        D0, D1 = Dstar, res.deltas
        if cameras_json is not None:
            from rigbuild.eval.frames import calibrated_to_ground_truth, vectors_to_ground_truth

            sim = calibrated_to_ground_truth(gt_dir, cameras_json)
            D0, D1 = vectors_to_ground_truth(Dstar, sim), vectors_to_ground_truth(res.deltas, sim)
        metrics.update(ground_truth_metrics(gt_dir, template.shape_names, D0, D1, region,
                                            res.weights, seq_col, frame_col,
                                            ho.get("final", {}).get("weights"),
                                            np.concatenate([np.full(data[s]["vertices"].shape[0], s) for s in held]) if held else None,
                                            np.concatenate([frame_numbers(data[s]) for s in held]) if held else None))
    write_json(out / "personalize_metrics.json", metrics)
    if metrics_path is not None:
        merge_metrics(metrics_path, "personalization", metrics)
    return metrics
