"""The retargeting jobs: rule ``retarget_ribera`` (:func:`run_ribera`), rule ``retarget_seol`` (:func:`run_seol`) and
rule ``take_markers`` (:func:`run_take_markers`: the tracked range of motion at a take's own markers).

Each reads the performance take, the actor's tracked ROM markers and the character rig, solves, and writes the
weight curves (CSV, JSON), the glTF animation, a figure, and its metrics fragment
``{"retarget": {<prefix>: {<character>: {...}}}}`` (prefixes: :mod:`rigbuild.retarget.methods`). The fragment's
keys name the method and the character, not the performance: a session's first performance is the one
gathered into metrics.json (``retarget_metric_files`` in rules/retarget.smk).
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any, Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.curves import write_weight_curves_csv, write_weight_curves_json
from rigbuild.io.gltf_anim import write_gltf_animation
from rigbuild.io.markers import MarkerTake, is_marker_sequences, read_marker_sequences, read_markers
from rigbuild.io.metrics import write_metrics_fragment
from rigbuild.io.rigs import read_rig_npz
from rigbuild.params import as_dict
from rigbuild.retarget.common import check_marker_overlap
from rigbuild.retarget.methods import (METHOD_KEYS, RIBERA_METHODS, RIBERA_RIG_METHODS, method_metrics,
                                       seol_result_metrics)
from rigbuild.retarget.params import ribera_from_config, seol_from_config

Path = str | os.PathLike


def plausibility_values(weights: np.ndarray, shape_names: Sequence[str]) -> dict[str, float]:
    """The gates a real capture is judged by (no ground truth): the fraction of frames with an antagonist
    pair both above 0.3 and the mean number of shapes above 0.1 (:func:`rigbuild.retarget.plausible.plausibility_metrics`)."""
    from rigbuild.retarget.plausible import plausibility_metrics

    m = plausibility_metrics(weights, shape_names)
    return {"antagonist_fraction": m["antagonist_fraction"], "mean_active": m["mean_active"]}


def ribera_job_metrics(res, n_markers: int) -> dict[str, Any]:
    """A Ribera job's numbers: timings (s), frames/s, frame and marker counts, weight range, the RMS second
    difference of the weight curves (per frame^2), the number of key expressions of the transfer, the fit's
    RMS marker residual (mm) and the plausibility numbers (:func:`plausibility_values`)."""
    F = res.weights.shape[0]
    jitter = float(np.sqrt(np.mean(np.diff(res.weights, 2, axis=0) ** 2))) if F > 2 else 0.0
    values = {"build_s": res.timings["build_s"], "retarget_s": res.timings["retarget_s"],
              "frames_per_s": F / max(res.timings["retarget_s"], 1e-9), "n_frames": F,
              "n_markers": int(n_markers), "empty_frames": int(res.empty_frames.size),
              "weight_min": float(res.weights.min()), "weight_max": float(res.weights.max()),
              "second_difference_rms": jitter, "marker_residual_mm": float(res.marker_residual_mm),
              **plausibility_values(res.weights, res.shape_names)}
    if res.model.transfer is not None:
        values["n_keys"] = int(res.model.transfer.keys.size)
        for key in ("rig_guess_shapes", "rig_guess_markers", "rig_alignment_rms_mm"):  # ribera_fit_actor_rig
            if key in res.model.transfer.info:
                values[key] = res.model.transfer.info[key]
    return values


def one_input(files) -> str | None:
    """A named job input that is one path or a list of at most one ([] where the rule gives none): the path,
    or None."""
    if files is None or isinstance(files, (str, os.PathLike)):
        return None if files is None else str(files)
    files = [str(f) for f in files]
    if len(files) > 1:
        raise InputError(f"expected one file, got {len(files)}: {files[:3]}", path="rules")
    return files[0] if files else None


def rom_takes(files: Sequence[Path]) -> tuple[list[MarkerTake], list[str]]:
    """The range-of-motion takes of a list of marker files, in order, and where each comes from (for errors): a
    file of several sequences (rule ``take_markers``, :func:`rigbuild.io.markers.write_marker_sequences`) gives
    each of its sequences, any other marker file one take."""
    takes, sources = [], []
    for f in files:
        if is_marker_sequences(f):
            for name, take in read_marker_sequences(f):
                takes.append(take)
                sources.append(f"{f} (sequence {name})")
        else:
            takes.append(read_markers(f))
            sources.append(str(f))
    return takes, sources


def run_take_markers(performance: Path, session_dir: Path, neutral: Path, vertices: Sequence[Path],
                     track: Mapping[str, Any] | None, take_markers: Mapping[str, Any] | None, *,
                     marker_map: Path, rom_markers: Path, metrics: Path) -> dict[str, Any]:
    """Rule ``take_markers``: a take's markers placed on the tracked neutral's skin
    (:func:`rigbuild.retarget.actor_rig.place_markers_on_neutral`) and the tracked range of motion read there.

    performance : .c3d/.npz markers; session_dir : the session (its template rig and fps); neutral : the
    tracked ``neutral.npz``; vertices : every ROM sequence's tracked ``vertices.npz`` (session order); track :
    ``params.track`` (the template rig tracked with); take_markers : ``params.retarget.take_markers``. Writes
    ``marker_map.json`` (marker -> face, barycentric, normal offset on the tracked topology, in the capture
    frame of the tracked neutral), ``rom_markers.npz`` (every sequence's markers at the map, lost frames as gaps:
    :func:`rigbuild.io.markers.write_marker_sequences`) and the fragment ``retarget.take_markers``."""
    from pathlib import Path as _P

    from rigbuild.io.atomic import write_json
    from rigbuild.io.markers import write_marker_sequences
    from rigbuild.retarget.actor_rig import marker_map_for_take, place_markers_on_neutral
    from rigbuild.retarget.params import take_markers_from_config
    from rigbuild.session import read_session
    from rigbuild.track.params import from_config as track_from_config
    from rigbuild.track.stage import load_template

    p = take_markers_from_config(take_markers)
    spec = read_session(_P(session_dir))
    template = load_template(spec, track_from_config(track))
    take = read_markers(performance)
    with np.load(neutral) as z:
        if "vertices" not in z or z["vertices"].shape != template.neutral.shape:
            raise InputError(f"the tracked neutral does not have the template's {template.n_vertices} vertices",
                             path=neutral, fix="re-run rule track_neutral with the same params.track.template_rig")
        neutral_v = z["vertices"].astype(np.float64)
    t0 = time.perf_counter()
    start = marker_map_for_take(template, take.names, path=performance)
    mmap = place_markers_on_neutral(neutral_v, template.faces, take.markers, start, p.neutral_fraction,
                                    p.min_frames, p.iterations, p.trim)
    seconds = time.perf_counter() - t0
    on_map = tracked_sequences_on_map(vertices, template.faces, mmap)
    sequences = {_P(f).parent.name: seq for f, seq in zip(vertices, on_map)}
    unplaced = [n for n, ok in zip(mmap.names, mmap.placed) if not ok]
    if unplaced:
        logging.getLogger("rigbuild.retarget").warning(
            "%s: markers %s are gaps in every frame that places the markers: they keep their marker-set vertex",
            performance, unplaced[:6])
    write_json(marker_map, {"rig": str(track_from_config(track).template_for(spec)), "neutral": str(neutral),
                            "performance": str(performance), "frame": "the tracked neutral's (capture) frame",
                            "surface_rms_mm": mmap.surface_rms_mm, "markers": mmap.to_json()})
    write_marker_sequences(rom_markers, sequences, mmap.names, spec.fps)
    values = {"n_markers": len(mmap.names), "surface_rms_mm": mmap.surface_rms_mm, "markers_unplaced": len(unplaced),
              "seconds": seconds}
    write_metrics_fragment(metrics, "retarget", {"take_markers": values})
    logging.getLogger("rigbuild.retarget").info(
        "%s: %d markers placed on the tracked neutral in %.2f s (skin RMS %.2f mm); %d ROM sequences read there",
        performance, len(mmap.names), seconds, mmap.surface_rms_mm, len(sequences))
    return values


def tracked_sequences_on_map(files: Sequence[Path], faces: np.ndarray,
                             marker_map) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each tracked ROM sequence (``vertices.npz``: vertices F x V x 3 mm, frames, lost) read at a marker map's skin
    points (:func:`rigbuild.retarget.actor_rig.tracked_markers_on_map`; lost frames are gaps): (markers (F, M, 3)
    mm, frame numbers (F,)) per file."""
    from rigbuild.retarget.actor_rig import tracked_markers_on_map

    out = []
    for f in files:
        with np.load(f) as z:
            if "vertices" not in z:
                raise InputError("a tracked sequence without vertices", path=f, fix="re-run the track rules")
            lost = z["lost"] if "lost" in z else None
            frames = z["frames"] if "frames" in z else np.arange(z["vertices"].shape[0])
            out.append((tracked_markers_on_map(z["vertices"], faces, marker_map, lost), frames))
    return out


def tracked_takes_on_map(files: Sequence[Path], rig_path: Path, marker_map_path: Path, fps: float) -> list:
    """The tracked ROM sequences (:func:`tracked_sequences_on_map`) at a take's marker map on the personalized
    rig, as marker takes."""
    import json

    from rigbuild.io.rigs import load_rig
    from rigbuild.retarget.actor_rig import MarkerMap

    faces = load_rig(rig_path, units="mm").faces
    mmap = MarkerMap.from_json(json.loads(open(marker_map_path).read())["markers"], path=marker_map_path)
    return [MarkerTake(markers, list(mmap.names), float(fps))
            for markers, _ in tracked_sequences_on_map(files, faces, mmap)]


def actor_rig_for_method(method: str, rig_methods: Sequence[str], rule: str, actor_rig: str | None,
                         marker_map: str | None, actor_solve: str | None = None):
    """The rig (personalized ``rig.npz`` or the template rig's spec) at the take's markers
    (:func:`load_rig_at_markers`) when ``method`` is one of the rule's ``rig_methods`` (InputError naming the rule
    when its inputs are missing); None for the other methods."""
    if method not in rig_methods:
        return None
    if not actor_rig or not marker_map:
        raise InputError(f"method '{method}' needs its rig and the take's marker map on it", path="rules",
                         fix=f"give rule {rule} the rig (params guess_rig) and the input marker_map for this method")
    return load_rig_at_markers(actor_rig, marker_map, actor_solve)


def refined_rig_at_markers(solve_path: Path, b0: np.ndarray, D: np.ndarray,
                           marker_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """The rig at the markers the take's actor-rig solve ended with (``solve.npz`` of rule ``actor_rig_weights``:
    ``rig_neutral_at_markers`` (M, 3), ``rig_deltas_at_markers`` (K, M, 3) mm, refined on the take with
    ``params.retarget.actor_rig.refine_iterations``), in place of the personalized rig's ``b0``, ``D`` at the same
    markers; ``b0``, ``D`` unchanged when the solve holds none (a solve.npz written before the refinement)."""
    try:
        with np.load(solve_path, allow_pickle=False) as z:
            if "rig_neutral_at_markers" not in z.files:
                return b0, D
            b1, D1 = z["rig_neutral_at_markers"].astype(np.float64), z["rig_deltas_at_markers"].astype(np.float64)
            names = [str(n) for n in z["marker_names"]]
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"cannot read the actor-rig solve ({e})", path=solve_path,
                         fix="re-run rule actor_rig_weights for this performance") from None
    if names != list(marker_names) or b1.shape != b0.shape or D1.shape != D.shape:
        raise InputError("the actor-rig solve and the marker map name other markers or shapes", path=solve_path,
                         fix="re-run rule actor_rig_weights for this performance (both come from its one job)")
    return b1, D1


def load_rig_at_markers(rig_path: Path, marker_map_path: Path, solve_path: Path | None = None):
    """The personalized rig (``rig.npz``; or any rig spec of :func:`rigbuild.io.rigs.load_rig`, e.g. the template
    rig's; mm) sampled at a take's markers placed on it (``marker_map.json`` of rule ``actor_rig_weights``):
    :class:`~rigbuild.retarget.ribera.RigAtMarkers` in the rig's frame; with the
    same job's ``solve.npz``, the rig at the markers refined on the take (:func:`refined_rig_at_markers`)."""
    import json

    from rigbuild.io.rigs import load_rig
    from rigbuild.retarget.actor_rig import MarkerMap, sample_rig_at_markers
    from rigbuild.retarget.ribera import RigAtMarkers

    rig = load_rig(rig_path, units="mm")
    try:
        doc = json.loads(open(marker_map_path).read())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the marker map ({e})", path=marker_map_path,
                         fix="re-run rule actor_rig_weights for this performance") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("markers"), dict):
        raise InputError("the marker map has no 'markers' mapping", path=marker_map_path,
                         fix="re-run rule actor_rig_weights for this performance")
    mmap = MarkerMap.from_json(doc["markers"], path=marker_map_path)
    n_faces = int(np.asarray(rig.faces).shape[0])
    if mmap.face_ids.size and (mmap.face_ids.min() < 0 or mmap.face_ids.max() >= n_faces):
        raise InputError(f"the marker map names triangles outside the rig's {n_faces}",
                         path=marker_map_path, fix=f"place the markers on {rig_path} (rule actor_rig_weights)")
    b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, mmap)
    if solve_path is not None:
        b0, D = refined_rig_at_markers(solve_path, b0, D, mmap.names)
    return RigAtMarkers(b0, D, list(mmap.names), [str(n) for n in rig.shape_names])


def run_ribera(performance: Path, training: Sequence[Path], rig_path: Path, method: str, character: str,
               performance_name: str, ribera: Mapping[str, Any] | None, neutral_frames: Sequence[int] | None, *,
               weights: Path, weights_json: Path, gltf: Path, preview: Path, metrics: Path,
               workers: int = 1, actor_rig: Path | Sequence[Path] | None = None,
               marker_map: Path | Sequence[Path] | None = None,
               actor_solve: Path | Sequence[Path] | None = None) -> dict[str, Any]:
    """Rule ``retarget_ribera``: one performance onto one character with one method of
    :data:`~rigbuild.retarget.methods.RIBERA_METHODS`.

    performance : .c3d/.npz markers; training : tracked ROM marker .npz files (``markers`` F x M x 3 mm,
    ``marker_names``); rig_path : character .npz with its marker map; ribera : ``params.retarget.ribera``;
    neutral_frames : the neutral row of each training file; method ``ribera`` runs with the paper's constants
    whatever ``ribera`` says (:meth:`~rigbuild.retarget.params.RiberaParams.for_method`; the weight files'
    ``params`` are the ones it ran with); actor_rig, marker_map : methods of
    :data:`~rigbuild.retarget.methods.RIBERA_RIG_METHODS` only, the personalized ``rig.npz`` (or the template rig's
    spec) and the take's ``marker_map.json`` on it (its guesses g_k,
    :func:`load_rig_at_markers`; actor_solve: the same job's ``solve.npz``, whose rig at the markers refined on the
    take replaces them), each a path or a list of at most one (:func:`one_input`); with them,
    ``training`` may be the tracked ``vertices.npz`` files, sampled at the marker map
    (:func:`tracked_takes_on_map`: the range of motion at the performance's own marker points). Writes the outputs
    named by the keywords; returns the metrics."""
    from rigbuild.retarget.preview import write_preview
    from rigbuild.retarget.run import make_training_set, retarget_performance

    p = ribera_from_config(ribera)
    if method not in RIBERA_METHODS:
        raise InputError(f"unknown method '{method}'", path="config", fix=f"use one of {RIBERA_METHODS}")
    p = p.for_method(method)  # ``ribera``: the paper's constants whatever the config says
    actor_rig, marker_map = one_input(actor_rig), one_input(marker_map)
    rig_at_markers = actor_rig_for_method(method, RIBERA_RIG_METHODS, "retarget_ribera", actor_rig, marker_map,
                                          one_input(actor_solve))
    take = read_markers(performance)
    files = list(training)
    if rig_at_markers is not None and all(str(f).endswith("vertices.npz") for f in files):
        takes = tracked_takes_on_map(files, actor_rig, marker_map, take.fps)
    else:
        takes, files = rom_takes(files)
    ts = make_training_set([t.markers for t in takes], [t.names for t in takes], list(neutral_frames or [0]), files)
    rig = read_rig_npz(rig_path)
    if rig.marker_vertices.size == 0:
        raise InputError(f"character '{rig.name}' has no marker map", path=rig_path,
                         fix="build the character with the session's marker set")
    check_marker_overlap(take.names, rig.marker_names, "the performance", performance, rig.name)
    for f, t in zip(files, takes):
        check_marker_overlap(t.names, rig.marker_names, "the training sequence", f, rig.name)
    res = retarget_performance(ts, take.markers, take.names, rig, rig.marker_names, rig.marker_vertices, method,
                               p.transfer_params(method), p.retarget_params(method),
                               allow_empty_frames=bool(p.allow_empty_frames), performance_path=performance,
                               map_path=rig_path, workers=int(workers),
                               marker_lowpass_hz=None if p.marker_lowpass_hz is None else float(p.marker_lowpass_hz),
                               fps=take.fps, actor_rig=rig_at_markers)
    fps = take.fps
    meta = {"method": method, "character": rig.name, "params": as_dict(p)}
    if rig_at_markers is not None:
        meta.update(actor_rig=str(actor_rig), marker_map=str(marker_map))
    write_weight_curves_csv(weights, res.weights, res.shape_names, fps)
    write_weight_curves_json(weights_json, res.weights, res.shape_names, fps, meta=meta)
    write_gltf_animation(gltf, rig, res.weights, fps)
    activity = np.abs(res.weights).sum(1)
    frames = sorted(set(np.argsort(-activity)[: max(1, int(p.preview_frames))].tolist()))
    write_preview(preview, res.stabilized, ts.neutral, rig, res.weights, frames, fps,
                  title=f"{performance_name} -> {rig.name} ({method})")
    values = ribera_job_metrics(res, len(ts.names))
    write_metrics_fragment(metrics, "retarget", method_metrics(method, character, values, p.primary))
    logging.getLogger("rigbuild.retarget.ribera").info(
        "%s %s -> %s: %d frames, build %.2f s, %.0f frames/s", method, performance_name, character,
        values["n_frames"], values["build_s"], values["frames_per_s"])
    return values


def seol_marker_residual(res) -> float:
    """RMS marker residual (mm) of a Seol solution: ``|s_t - B w_t|`` per visible marker, in the source's
    stabilized space (the scale-matched target shapes B)."""
    S, B = res.system.S, res.system.B
    d = (S - res.weights @ B.T).reshape(S.shape[0], -1, 3)
    d2 = np.sum(d * d, axis=2)
    vis = res.system.visibility
    return float(np.sqrt(d2.mean() if vis is None else d2[vis].mean()))


def seol_neutral(files: Sequence[Path], frames: Sequence[int] | None, names: Sequence[str]) -> np.ndarray:
    """The actor's neutral (M, 3) mm in ``names`` order: the rigidly aligned mean of row ``frames[i]`` of each
    tracked ROM sequence ``i`` of ``files`` (:func:`rom_takes`; default row 0 of each)."""
    from rigbuild.retarget.common import average_neutral, reorder_markers

    takes, sources = rom_takes(list(files))
    frames = list(frames or [0] * len(takes))
    if len(frames) != len(takes):
        raise InputError(f"{len(takes)} neutral marker sequences but {len(frames)} neutral frames", path="rules",
                         fix="give one neutral frame per ROM sequence")
    rows = []
    for rom, path, frame in zip(takes, sources, frames):
        if not 0 <= int(frame) < rom.markers.shape[0]:
            raise InputError(f"neutral frame {frame} outside the {rom.markers.shape[0]} frames", path=path)
        rows.append(reorder_markers(rom.markers, rom.names, names, what="neutral sequence", path=path)[int(frame)])
    return average_neutral(np.stack(rows))


def run_seol(performance: Path, rig_path: Path, neutral: Sequence[Path] | None, neutral_frames: Sequence[int] | None,
             character: str, performance_name: str, seol: Mapping[str, Any] | None, *, weights: Path,
             weights_json: Path, gltf: Path, plot: Path, metrics: Path, system: Path, method: str = "seol",
             actor_rig: Path | Sequence[Path] | None = None,
             marker_map: Path | Sequence[Path] | None = None,
             actor_solve: Path | Sequence[Path] | None = None) -> dict[str, Any]:
    """Rule ``retarget_seol``: spacetime expression cloning (Seol et al. 2012) of one performance onto one
    character, with the sec. 7 per-frame baselines, the fig. 11 velocity-error plot and ``system.npz`` for
    ``rigbuild edit``.

    neutral : tracked ROM marker files whose rows ``neutral_frames`` are neutral poses (None: the take's first
    frame); seol : ``params.retarget.seol``; method : one of :data:`~rigbuild.retarget.methods.SEOL_METHODS`;
    actor_rig, marker_map : method ``seol_actor_rig`` only, the personalized ``rig.npz`` and the take's
    ``marker_map.json`` on it (:func:`load_rig_at_markers`; the source neutral and expression space,
    :mod:`rigbuild.retarget.seol.actor_space`; actor_solve: the same job's ``solve.npz``, whose rig at the markers
    refined on the take replaces them), each a path or a list of at most one (:func:`one_input`).
    Writes the outputs named by the keywords; returns the metrics."""
    from rigbuild.retarget.common import reorder_markers
    from rigbuild.retarget.seol import retarget_seol
    from rigbuild.retarget.seol_outputs import plot_velocity_error

    from rigbuild.retarget.methods import SEOL_METHODS, SEOL_RIG_METHODS

    if method not in SEOL_METHODS:
        raise InputError(f"unknown method '{method}'", path="rules", fix=f"use one of {SEOL_METHODS}")
    p = seol_from_config(seol).for_method(method)
    actor_rig, marker_map = one_input(actor_rig), one_input(marker_map)
    rig_at_markers = actor_rig_for_method(method, SEOL_RIG_METHODS, "retarget_seol", actor_rig, marker_map,
                                          one_input(actor_solve))
    t0 = time.perf_counter()
    take = read_markers(performance)
    rig = read_rig_npz(rig_path)
    check_marker_overlap(take.names, rig.marker_names, "the performance", performance, rig.name)
    names = [n for n in rig.marker_names if n in set(take.names)]
    if len(names) < 4:
        raise InputError(f"only {len(names)} markers of the take are on character '{rig.name}'", path=performance,
                         fix="use a character marker map with the take's marker names")
    X = reorder_markers(take.markers, take.names, names, path=performance)
    Y = None if not neutral else seol_neutral([neutral] if isinstance(neutral, str) else neutral, neutral_frames, names)
    res = retarget_seol(X, rig, marker_names=names, source_neutral=Y, params=p, fps=float(take.fps),
                        source_path=performance, actor_rig=rig_at_markers)
    seconds = time.perf_counter() - t0
    fps = take.fps
    meta = {"method": "seol2012", "alpha": res.alpha, "character": rig.name, "scale_match": p.scale_match,
            "params": as_dict(p)}
    if rig_at_markers is not None:
        meta.update(method="seol2012_actor_rig", actor_rig=str(actor_rig), marker_map=str(marker_map))
    write_weight_curves_csv(weights, res.weights, res.shape_names, fps)
    write_weight_curves_json(weights_json, res.weights, res.shape_names, fps, meta=meta)
    # head motion and pivot are in mm: write the character in mm too
    write_gltf_animation(gltf, rig if rig.units == "mm" else rig.to_units("mm"), res.weights, fps,
                         res.head_rotation, res.head_translation, pivot=res.target_pivot)
    plot_velocity_error(plot, res.velocity_error, fps, title=f"{performance_name} -> {rig.name}")
    res.system.save(system)
    values = {"seconds": seconds, "n_frames": int(X.shape[0]), "n_markers": len(names), "alpha": res.alpha,
              "marker_residual_mm": seol_marker_residual(res),
              "second_difference_rms": float(np.sqrt(np.mean(np.diff(res.weights, 2, axis=0) ** 2)))
              if res.weights.shape[0] > 2 else 0.0, **plausibility_values(res.weights, res.shape_names)}
    if res.actor_space is not None:  # seol_actor_rig: how much of the source side the personalized rig gave
        values.update(rig_space_shapes=int(res.actor_space.shapes.sum()),
                      rig_space_markers=int(res.actor_space.markers.sum()),
                      rig_alignment_rms_mm=float(res.actor_space.alignment_rms_mm))
    per_result = {}
    for name, curve in res.velocity_error.items():
        W = res.weights if name == "spacetime" else res.baselines[name]
        per_result[name] = {"velocity_error": float(curve.sum()), "weight_min": float(W.min()),
                            "weight_max": float(W.max())}
    body = seol_result_metrics(per_result, character, method)
    key = METHOD_KEYS[method]
    body[key][str(character)] = {**values, **body[key][str(character)]}
    write_metrics_fragment(metrics, "retarget", body)
    logging.getLogger("rigbuild.retarget.seol").info(
        "%s %s -> %s: %d frames in %.2f s, velocity error %.1f (Range PF %.1f, Prior PF %.1f)", method,
        performance_name, character, X.shape[0], seconds, per_result["spacetime"]["velocity_error"],
        per_result["perframe_range"]["velocity_error"], per_result["perframe_prior"]["velocity_error"])
    return {key: values, **per_result}


# ------------------------------------------------------------------------------- the actor's own rig
def run_actor_rig(performance: Path, rig_path: Path, actor_rig: Mapping[str, Any] | None, performance_name: str, *,
                  source: str = "actor_rig", marker_map: Path, weights: Path, weights_json: Path, solve: Path, metrics: Path) -> dict[str, Any]:
    """Rule ``actor_rig_weights``: a take's markers placed on the personalized rig and the actor's weights
    solved from that rig (:mod:`rigbuild.retarget.actor_rig`).

    performance : .c3d/.npz markers (any rigid frame, NaN gaps); rig_path : the personalized ``rig.npz`` (its
    marker set names the take's markers and starts the map); actor_rig : ``params.retarget.actor_rig``.
    Writes ``marker_map.json`` (marker -> face, barycentric, normal offset on the rig), the weight curves (CSV,
    JSON, the rig's shape order), ``solve.npz`` (weights (F, K), rotations (F, 3, 3), translations (F, 3) mm:
    rig frame -> take frame, residual_mm (F,); with ``refine_iterations`` the solve from the unrefined rig as
    unrefined_weights / unrefined_residual_mm and the rig at the markers it ended with, rig_neutral_at_markers
    (M, 3), rig_deltas_at_markers (K, M, 3) mm) and the metrics fragment ``retarget.actor_rig_weights``."""
    from rigbuild.io.atomic import save_npz, write_json
    from rigbuild.retarget.actor_rig import (fit_marker_map, marker_map_for_take, sample_rig_at_markers,
                                             solve_actor_weights_refined)
    from rigbuild.retarget.common import lowpass_markers
    from rigbuild.retarget.params import actor_rig_from_config

    p = actor_rig_from_config(actor_rig)
    take = read_markers(performance)
    from rigbuild.io.rigs import load_rig

    rig = load_rig(rig_path, units="mm")
    start = marker_map_for_take(rig, take.names, path=rig_path)
    P = take.markers if p.marker_lowpass_hz is None else lowpass_markers(take.markers, take.fps, p.marker_lowpass_hz)
    t0 = time.perf_counter()
    mmap = fit_marker_map(rig.neutral, rig.deltas, rig.faces, P, take.names, start, n_frames=p.map_frames,
                          iterations=p.map_iterations, lambda_l1=p.lambda_l1, bounds=p.bounds,
                          observable_mm=p.observable_mm)
    t1 = time.perf_counter()
    b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, mmap)
    lambda_t = p.temporal_weight(take.fps)
    sol, first, b0_refined, D_refined = solve_actor_weights_refined(
        b0, D, P, p.refine_iterations, p.refine_prior, lambda_t=lambda_t, lambda_l1=p.lambda_l1,
        lambda_s=p.lambda_s, bounds=p.bounds, sweeps=p.sweeps, tol=p.tol, observable_mm=p.observable_mm)
    t2 = time.perf_counter()
    far = [n for n, o in zip(mmap.names, mmap.normal_offset) if abs(o) > p.max_surface_distance_mm]
    log = logging.getLogger("rigbuild.retarget.actor_rig")
    if far:
        log.warning("%s: markers %s sit more than %.1f mm off the personalized rig's skin (%s): mislabelled or "
                    "loose markers, or a rig that does not fit this actor", performance, far[:6],
                    p.max_surface_distance_mm, rig_path)
    unplaced = [n for n, ok in zip(mmap.names, mmap.placed) if not ok]
    if unplaced:
        log.warning("%s: markers %s are gaps in every placing frame: they keep their marker-set vertex on the rig",
                    performance, unplaced[:6])
    if not sol.converged:
        log.warning("%s: the actor-rig solve stopped after %d sweeps before every weight settled to %.0e "
                    "(params.retarget.actor_rig.sweeps)", performance, sol.sweeps, p.tol)
    write_json(marker_map, {"rig": str(rig_path), "performance": str(performance), "frame": "the rig's (head) frame",
                            "surface_rms_mm": mmap.surface_rms_mm, "markers": mmap.to_json()})
    meta = {"method": source, "rig": str(rig_path), "params": as_dict(p)}
    write_weight_curves_csv(weights, sol.weights, rig.shape_names, take.fps)
    write_weight_curves_json(weights_json, sol.weights, rig.shape_names, take.fps, meta=meta)
    save_npz(solve, weights=sol.weights, rotations=sol.rotations, translations=sol.translations,
             residual_mm=sol.residual_mm, observable=sol.observable, shape_names=np.asarray(rig.shape_names),
             marker_names=np.asarray(mmap.names), fps=np.float64(take.fps), unrefined_weights=first.weights,
             unrefined_residual_mm=first.residual_mm, rig_neutral_at_markers=b0_refined,
             rig_deltas_at_markers=D_refined)
    F = sol.weights.shape[0]
    values = {"n_frames": F, "n_markers": len(mmap.names), "map_s": t1 - t0, "solve_s": t2 - t1,
              "frames_per_s": F / max(t2 - t1, 1e-9), "sweeps": sol.sweeps, "converged": sol.converged,
              "refine_iterations": p.refine_iterations, "lambda_t": lambda_t,
              "marker_residual_mm": float(np.nanmean(sol.residual_mm)),
              "unrefined_marker_residual_mm": float(np.nanmean(first.residual_mm)),
              "map_surface_rms_mm": mmap.surface_rms_mm, "markers_off_skin": len(far),
              "markers_unplaced": len(unplaced),
              "weight_min": float(sol.weights.min()), "weight_max": float(sol.weights.max()),
              **plausibility_values(sol.weights, rig.shape_names)}
    write_metrics_fragment(metrics, "retarget", {f"{source}_weights": values})
    log.info("%s: %d markers placed on the personalized rig in %.2f s; %d frames solved in %.2f s (%.0f frames/s), "
             "residual %.2f mm", performance_name, len(mmap.names), t1 - t0, F, t2 - t1, values["frames_per_s"],
             values["marker_residual_mm"])
    return values


def run_semantic(actor_weights: Path, solve: Path, rig_path: Path, actor_rig_path: Path, character: str,
                 performance_name: str, *, weights: Path, weights_json: Path, gltf: Path, preview: Path,
                 metrics: Path) -> dict[str, Any]:
    """Rule ``retarget_semantic``: the actor weights (from the personalized rig) carried to a character by shape
    name (:func:`rigbuild.retarget.actor_rig.semantic_transfer`), with the take's head motion; metrics under
    ``retarget.semantic_actor_rig.<character>``."""
    from rigbuild.io.curves import read_weight_curves_csv
    from rigbuild.retarget.actor_rig import semantic_transfer
    from rigbuild.retarget.methods import method_metrics
    from rigbuild.retarget.preview import write_preview

    t0 = time.perf_counter()
    W, names, _ = read_weight_curves_csv(actor_weights)
    with np.load(solve) as z:
        fps = float(z["fps"])
    rig = read_rig_npz(rig_path)
    Wc, shared = semantic_transfer(W, names, rig.shape_names)
    seconds = time.perf_counter() - t0
    write_weight_curves_csv(weights, Wc, rig.shape_names, fps)
    write_weight_curves_json(weights_json, Wc, rig.shape_names, fps,
                             meta={"method": "semantic_actor_rig", "character": rig.name, "actor_weights": str(actor_weights),
                                   "shared_shapes": len(shared)})
    write_gltf_animation(gltf, rig, Wc, fps)
    actor = read_rig_npz(actor_rig_path)
    activity = np.abs(Wc).sum(1)
    frames = sorted(set(np.argsort(-activity)[:4].tolist()))
    if actor.marker_vertices.size:
        neutral = actor.neutral[actor.marker_vertices]
        posed = neutral[None] + np.einsum("fk,kmc->fmc", W, actor.deltas[:, actor.marker_vertices])
        write_preview(preview, posed, neutral, rig, Wc, frames, fps,
                      title=f"{performance_name} -> {rig.name} (semantic_actor_rig)")
    else:
        raise InputError("the personalized rig has no marker set to preview the actor with", path=actor_rig_path)
    values = {"seconds": seconds, "n_frames": int(Wc.shape[0]), "shared_shapes": len(shared),
              "character_shapes": len(rig.shape_names), "weight_min": float(Wc.min()), "weight_max": float(Wc.max()),
              **plausibility_values(Wc, rig.shape_names)}
    write_metrics_fragment(metrics, "retarget", method_metrics("semantic_actor_rig", character, values))
    return values
