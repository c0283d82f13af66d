"""The personalization stage: tracked ROM sequences + template rig -> personalized rig and reports.

Called by ``scripts/personalize.py`` (rule ``personalize``, :func:`run_personalize`); usable without Snakemake
(tests, :func:`run_personalization`). Ground-truth evaluation of its outputs is a separate rule
(``eval_personalize``); this stage never reads the session's ground truth.

Files written under ``results/{session}/personalize/``: ``rig.npz``, ``initial_rig.npz`` (D* on the tracked
neutral), ``rig_obj/``, ``rig.gltf`` (the rig files, in the template's head frame: ``head_frame.json`` holds the
capture-to-head transform; :mod:`rigbuild.personalize.export`), ``weights.npz``, ``fit.npz`` (the fit, in the
cameras' world), ``objective.json``, ``convergence.png``, ``heatmaps/`` and the metrics fragment
``personalize_metrics.json`` (``{"personalization": {...}}``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.deformation_transfer import deformation_transfer_aligned
from rigbuild.io.atomic import save_npz, write_json
from rigbuild.io.metrics import write_metrics_fragment
from rigbuild.personalize.em import PersonalizationResult, fit_weights_and_rigid, personalize
from rigbuild.personalize.export import export_rigs
from rigbuild.personalize.params import PersonalizeConfig, from_config
from rigbuild.personalize.plots import plot_convergence, render_change_heatmap, render_change_overview
from rigbuild.rig import Rig

log = logging.getLogger(__name__)

#: the stage's metrics fragment (beside rig.npz) and its top-level key in metrics.json
METRICS_FILE = "personalize_metrics.json"
METRICS_KEY = "personalization"


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


def split_sequences(names: list[str], held_out: tuple[str, ...] | list[str]) -> tuple[list[str], list[str]]:
    """ROM sequence names -> (fitting sequences, held-out sequences); InputError when a held-out name is not
    a ROM sequence or nothing is left to fit."""
    held = [s for s in held_out if s in names]
    missing = [s for s in held_out if s not in names]
    if missing:
        raise InputError(f"held-out sequence(s) {missing} are not ROM sequences of this session", path="config",
                         fix=f"params.personalize.held_out_sequences must name some of: {', '.join(names)}")
    fit_names = [s for s in names if s not in held]
    if not fit_names:
        raise InputError("every ROM sequence is held out; nothing to fit", path="config",
                         fix="hold out fewer sequences in params.personalize.held_out_sequences")
    return fit_names, held


def tracked_neutral(data: Mapping[str, dict], cfg: PersonalizeConfig, fit_names: list[str],
                    neutral_frames: Mapping[str, int] | None) -> np.ndarray:
    """The actor's neutral b_0 (V, 3) mm: the neutral frame of the chosen sequence (``cfg.neutral_sequence``,
    default the first fitting one; ``cfg.neutral_frame``, default the sequence's ``neutral_frames`` entry;
    its first tracked frame when that frame is not tracked)."""
    nseq = cfg.neutral_sequence if cfg.neutral_sequence is not None else fit_names[0]
    if nseq not in data:
        raise InputError(f"neutral_sequence '{nseq}' is not a ROM sequence", path="config")
    nframe = cfg.neutral_frame if cfg.neutral_frame is not None else (neutral_frames or {}).get(nseq)
    fr = data[nseq]["frames"]
    idx = 0
    if nframe is not None and fr is not None:
        hits = np.flatnonzero(fr == int(nframe))
        idx = int(hits[0]) if hits.size else 0
    log.info("neutral: sequence %s, tracked frame index %d", nseq, idx)
    return data[nseq]["vertices"][idx]


def initial_shapes(template: Rig, b0: np.ndarray, workers: int = 1) -> np.ndarray:
    """D* (K, V, 3) mm: the template's shapes transferred onto the tracked neutral ``b0``. The tracked neutral is
    in the calibrated cameras' world, the template in its own: the template's shapes are turned with the template
    placed on b0 before their deformation gradients are transferred. InputError for an all-zero result."""
    Dstar = deformation_transfer_aligned(template.neutral, template.deltas, template.faces, b0,
                                         align_vertices=template.face_vertices, workers=workers)
    zero = [template.shape_names[k] for k in range(template.n_shapes) if not np.any(Dstar[k])]
    if zero:
        raise InputError(f"all-zero shape(s) in the template rig: {', '.join(zero)}",
                         fix="remove them from the template (config 'shapes:') or fix the rig files")
    return Dstar


def _stack(data: Mapping[str, dict], names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenated vertices (N, V, 3), confidence (N, V) and sequence index (N,) of sequences ``names``."""
    return (np.concatenate([data[s]["vertices"] for s in names]),
            np.concatenate([data[s]["confidence"] for s in names]),
            np.concatenate([np.full(data[s]["vertices"].shape[0], i) for i, s in enumerate(names)]))


def fit_held_out(data: Mapping[str, dict], held: list[str], b0: np.ndarray, Dstar: np.ndarray,
                 res: PersonalizationResult, region: np.ndarray | None, n_vertices: int, cfg: PersonalizeConfig,
                 neutral_frames: Mapping[str, int] | None) -> dict:
    """Weights and rigid motion of the held-out frames with the initial and with the personalized rig:
    ``{"initial": fit, "final": fit}`` (:func:`fit_weights_and_rigid` dicts); ``{}`` without held-out frames."""
    if not held:
        return {}
    hf, hc, hid = _stack(data, held)
    hc_fit = hc if region is None else np.where(np.isin(np.arange(n_vertices), region)[None], hc, 0.0)
    hn = neutral_frame_mask(data, held, neutral_frames)
    return {"initial": fit_weights_and_rigid(b0, Dstar, hf, hc_fit, hid, cfg.em, vertices=region, neutral_mask=hn),
            "final": fit_weights_and_rigid(res.neutral, res.deltas, hf, hc_fit, hid, cfg.em, vertices=region,
                                           neutral_mask=hn)}


def _column(data: Mapping[str, dict], names: list[str], of) -> np.ndarray:
    return np.concatenate([of(s) for s in names])


def write_fit_arrays(out: Path, data: Mapping[str, dict], fit_names: list[str], held: list[str], b0: np.ndarray,
                     Dstar: np.ndarray, res: PersonalizationResult, ho: dict, region: np.ndarray | None,
                     shape_names: list[str]) -> None:
    """``weights.npz``: per fitting frame weights (F, K), rotation, translation (float32), sequence, frame
    (session frame number), kept, shape_names, and with held-out sequences heldout_weights, heldout_rotation,
    heldout_translation, heldout_sequence, heldout_frame. ``fit.npz``: the fit at full precision (float64), in
    the cameras' world: the two rigs, initial_neutral (b0, V x 3 mm) + initial_deltas (D*, K x V x 3 mm) and
    neutral (V, 3) + deltas (K, V, 3) mm; each rig's fit of the fitting frames, initial_weights (F, K),
    initial_rotations (F, 3, 3), initial_translations (F, 3) mm (the EM's first weights step) and weights,
    rotations, translations (the personalized rig); with held-out sequences the same solve with each rig,
    heldout_initial_{weights,rotations,translations} and heldout_{weights,rotations,translations} (H rows);
    and fit_vertices (R,), the vertices the fit was restricted to (absent when every vertex was fitted)."""
    seq_col = _column(data, fit_names, lambda s: np.full(data[s]["vertices"].shape[0], s))
    frame_col = _column(data, fit_names, lambda s: frame_numbers(data[s]))
    arrays = dict(weights=res.weights.astype(np.float32), rotation=res.rotations.astype(np.float32),
                  translation=res.translations.astype(np.float32), sequence=seq_col, frame=frame_col,
                  kept=res.kept, shape_names=np.asarray(shape_names))
    fit = dict(initial_neutral=b0, initial_deltas=Dstar, neutral=res.neutral, deltas=res.deltas,
               initial_weights=res.initial_weights, initial_rotations=res.initial_rotations,
               initial_translations=res.initial_translations, weights=res.weights, rotations=res.rotations,
               translations=res.translations)
    if held:
        arrays.update(heldout_weights=ho["final"]["weights"].astype(np.float32),
                      heldout_rotation=ho["final"]["rotations"].astype(np.float32),
                      heldout_translation=ho["final"]["translations"].astype(np.float32),
                      heldout_sequence=_column(data, held, lambda s: np.full(data[s]["vertices"].shape[0], s)),
                      heldout_frame=_column(data, held, lambda s: frame_numbers(data[s])))
        fit.update({f"heldout_{pre}{k}": ho[which][k] for pre, which in (("", "final"), ("initial_", "initial"))
                    for k in ("weights", "rotations", "translations")})
    if region is not None:
        fit.update(fit_vertices=np.asarray(region, dtype=np.int64))
    save_npz(out / "weights.npz", **arrays)
    save_npz(out / "fit.npz", **fit)


def write_figures(out: Path, template: Rig, b0: np.ndarray, Dstar: np.ndarray, res: PersonalizationResult,
                  region: np.ndarray | None, heatmaps: bool) -> None:
    """``convergence.png`` and ``heatmaps/`` (the overview; one per shape with ``heatmaps``)."""
    plot_convergence(res.objective, out / "convergence.png")
    hm = out / "heatmaps"
    hm.mkdir(exist_ok=True)
    render_change_overview(b0, Dstar, res.deltas, template.faces, template.shape_names, hm / "overview.png", region)
    if heatmaps:
        for k, name in enumerate(template.shape_names):
            render_change_heatmap(b0, Dstar[k], res.deltas[k], template.faces, hm / f"{name}.png", name, region)


def stage_metrics(res: PersonalizationResult, ho: dict) -> dict:
    """The stage's metrics (``personalization.<key>``): fit residuals (mm) on the fitting and, with ``ho``, the
    held-out frames, EM convergence and timings. The residuals are the plain RMS over the confident vertices
    (``residual_*``, ``heldout_residual_*``: the headline) and weighted by the tracking confidence as the EM's
    data term (``*_weighted``)."""
    metrics = {
        "residual_initial_mm": res.residual_initial_unweighted_mm,
        "residual_final_mm": res.residual_final_unweighted_mm,
        "residual_reduction": 1.0 - res.residual_final_unweighted_mm / res.residual_initial_unweighted_mm,
        "residual_initial_weighted_mm": res.residual_initial_mm,
        "residual_final_weighted_mm": res.residual_final_mm,
        "residual_reduction_weighted": 1.0 - res.residual_final_mm / res.residual_initial_mm,
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
    if ho:
        metrics.update(heldout_residual_initial_mm=ho["initial"]["rms_unweighted_mm"],
                       heldout_residual_final_mm=ho["final"]["rms_unweighted_mm"],
                       heldout_residual_reduction=1.0 - ho["final"]["rms_unweighted_mm"]
                       / ho["initial"]["rms_unweighted_mm"],
                       heldout_residual_initial_weighted_mm=ho["initial"]["rms_mm"],
                       heldout_residual_final_weighted_mm=ho["final"]["rms_mm"],
                       heldout_residual_reduction_weighted=1.0 - ho["final"]["rms_mm"] / ho["initial"]["rms_mm"])
    return metrics


def run_personalization(
    tracks: Mapping[str, str | os.PathLike],
    template: Rig,
    out_dir: str | os.PathLike,
    cfg: PersonalizeConfig | Mapping | None = None,
    neutral_frames: Mapping[str, int] | None = None,
    workers: int = 1,
) -> dict:
    """Run the whole stage.

    tracks : sequence name -> vertices.npz (in session order).
    template : the template rig (mm), same topology as the tracked meshes.
    out_dir : results/{session}/personalize (every file it writes is listed in the module docstring).
    cfg : :class:`PersonalizeConfig` (a ``config["params"]["personalize"]`` mapping is passed through
        :func:`rigbuild.personalize.params.from_config`).
    neutral_frames : sequence -> the session frame number of its neutral pose (SequenceSpec.neutral_frame).
    workers : processes for the initial rig's per-shape deformation transfer (the job's threads).

    Returns the stage's metrics (also written as the fragment ``personalize_metrics.json``).
    """
    cfg = from_config(cfg)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(tracks)
    fit_names, held = split_sequences(names, cfg.held_out_sequences)
    data = {s: read_tracked_sequence(tracks[s], template.n_vertices) for s in names}
    b0 = tracked_neutral(data, cfg, fit_names, neutral_frames)
    region = template.face_vertices if cfg.fit_region == "face" else None
    Dstar = initial_shapes(template, b0, workers)

    frames, conf, seq_ids = _stack(data, fit_names)
    res = personalize(b0, Dstar, template.faces, frames, conf, seq_ids, cfg.em, template.shape_names, region,
                      neutral_mask=neutral_frame_mask(data, fit_names, neutral_frames))
    for m in res.warnings:
        log.warning("%s", m)

    rig = dataclasses.replace(template.copy(), neutral=res.neutral, deltas=res.deltas, name="personalized")
    initial = dataclasses.replace(template.copy(), neutral=b0, deltas=Dstar, name="initial")
    export_rigs(out, rig, initial, template, cfg.export)

    ho = fit_held_out(data, held, b0, Dstar, res, region, template.n_vertices, cfg, neutral_frames)
    write_fit_arrays(out, data, fit_names, held, b0, Dstar, res, ho, region, template.shape_names)
    write_json(out / "objective.json", {"objective": res.objective, "timings": res.timings,
                                         "n_free_variables": res.n_free_variables, "warnings": res.warnings,
                                         "params": dataclasses.asdict(cfg.em), "fit_sequences": fit_names,
                                         "held_out_sequences": held})
    write_figures(out, template, b0, Dstar, res, region, cfg.heatmaps)
    metrics = stage_metrics(res, ho)
    write_metrics_fragment(out / METRICS_FILE, METRICS_KEY, metrics)
    return metrics


def load_template(spec: str) -> Rig:
    """The template rig of a rig spec (``ict``: the ICT-FaceKit model under ``$RIGBUILD_DATA``)."""
    from rigbuild.io.rigs import load_rig
    from rigbuild.paths import ict_dir

    return load_rig(ict_dir() if spec == "ict" else spec)


def run_personalize(tracks: Mapping[str, str | os.PathLike], template_rig: str, out_dir: str | os.PathLike,
                    params: Mapping | None, neutral_frames: Mapping[str, int] | None, workers: int = 1) -> dict:
    """Rule ``personalize``: ``params`` is the raw ``config["params"]["personalize"]`` block, ``template_rig``
    the resolved rig spec; see :func:`run_personalization`."""
    cfg = from_config(params)
    return run_personalization(tracks, load_template(str(template_rig)), out_dir, cfg, neutral_frames, workers)
