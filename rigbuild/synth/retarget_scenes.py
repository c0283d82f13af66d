"""Retargeting test data: ground-truth scenes of a synthetic actor, and the target characters.

- :func:`synthetic_retarget_scene`: a range-of-motion training set and a speech-like performance of an actor
  (Ribera et al. 2017 protocol) with the ground-truth weights;
- :func:`synthetic_performance`: the Seol et al. 2012 capture protocol (neutral face at the start and the end,
  speech-like weights, smooth head motion, marker noise, optional gaps);
- :func:`run_character_rig`: rule ``character_rig`` (config ``characters:``): a template copy or a stylized
  variant of a rig (:func:`rigbuild.synth.characters.make_character`) written as an npz.
"""

from __future__ import annotations

import json
import os
from typing import Any, Mapping

import numpy as np

from rigbuild.rig import Rig


def neutral_envelope(n_frames: int, ramp_frames: int) -> np.ndarray:
    """(F,) 0 at the first and last frame, smoothstep up to 1 over ``ramp_frames`` frames at each end."""
    i = np.arange(n_frames, dtype=np.float64)
    x = np.clip(np.minimum(i, n_frames - 1 - i) / max(ramp_frames, 1), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def synthetic_performance(
    template: Rig,
    n_frames: int = 600,
    fps: float = 60.0,
    seed: int = 0,
    noise_mm: float = 0.05,
    gap_fraction: float = 0.0,
    head_motion: bool = True,
    ramp_frames: int = 30,
    actor_kwargs: Mapping | None = None,
) -> dict:
    """A synthetic performance of an actor derived from ``template`` (which carries the marker set).

    Returns ``{"actor": Rig, "info": dict, "weights": (F, K) ground truth, "markers": (F, M, 3) mm
    world space, "R": (F, 3, 3), "t": (F, 3), "fps"}``. Weights start and end at neutral (the
    paper's actors hold a neutral face at both ends, sec. 3.1).
    """
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.motion import make_head_motion, make_performance_weights, markers_from_rig

    actor, info = make_actor_rig(template, seed=seed, **dict(actor_kwargs or {}))
    W = make_performance_weights(template.shape_names, n_frames, fps, seed=seed + 1)
    W = W * neutral_envelope(n_frames, ramp_frames)[:, None]
    R = t = None
    if head_motion:
        R, t = make_head_motion(n_frames, seed=seed + 2)
    X = markers_from_rig(actor, W, R, t, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 3)
    return {"actor": actor, "info": info, "weights": W, "markers": X, "R": R, "t": t, "fps": fps}


def synthetic_retarget_scene(template, seed: int = 0, identity_folder=None, n_rom_sequences: int | None = None,
                             rom_frames: int = 20, rom_coverage: int = 2, perf_frames: int = 450, fps: float = 30.0,
                             noise_mm: float = 0.2, gap_fraction: float = 0.01) -> dict:
    """A ground-truth retargeting scene on ``template`` (a Rig with a marker set, mm).

    The actor (:func:`rigbuild.synth.actor.make_actor_rig`) performs a range-of-motion training set
    (``n_rom_sequences`` x ``rom_frames``, default one sequence per shape, each shape peaking in
    ``rom_coverage`` sequences) and a speech-like performance, both with head motion, marker noise and gaps.
    Returns a dict: actor, info, training (F, M, 3), segment_starts, rom_weights, neutral (M, 3),
    performance (F', M, 3), weights (F', K) ground truth, fps.
    """
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.motion import make_head_motion, make_performance_weights, make_rom_weights, markers_from_rig

    actor, info = make_actor_rig(template, seed=seed, identity_folder=identity_folder)
    names = actor.shape_names
    n_seq = n_rom_sequences or len(names)
    seqs = make_rom_weights(names, n_seq, rom_frames, seed=seed + 5, coverage=rom_coverage)
    W = np.concatenate(seqs)
    starts = np.cumsum([0] + [len(s) for s in seqs[:-1]]).astype(np.int64)
    R, t = make_head_motion(len(W), seed=seed + 6, max_rotation_deg=2.0, max_translation_mm=3.0)
    train = markers_from_rig(actor, W, R, t, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 7)
    train[0] = markers_from_rig(actor, W[:1], noise_mm=noise_mm, seed=seed + 8)[0]  # a clean neutral frame 0
    Wp = make_performance_weights(names, perf_frames, fps, seed=seed + 9)
    R2, t2 = make_head_motion(perf_frames, seed=seed + 10)
    perf = markers_from_rig(actor, Wp, R2, t2, noise_mm=noise_mm, gap_fraction=gap_fraction, seed=seed + 11)
    return {"actor": actor, "info": info, "training": train, "segment_starts": starts, "rom_weights": W,
            "neutral": train[0].copy(), "performance": perf, "weights": Wp, "fps": fps}


def run_character_rig(character: Mapping[str, Any], name: str, out_rig: str | os.PathLike) -> Rig:
    """Rule ``character_rig``: build character ``name`` from its config entry ``{rig, kind, markers?}`` (rig
    spec: procedural | ict | OBJ folder | rig npz; ``markers``: optional JSON marker map ``{name: vertex}``
    or ``{"markers": {...}}`` replacing the rig's) and write it to ``out_rig``."""
    from rigbuild.errors import InputError
    from rigbuild.io.rigs import load_rig, write_rig_npz
    from rigbuild.paths import ict_dir
    from rigbuild.synth.characters import make_character

    rig = load_rig(character["rig"])
    if character.get("markers"):
        with open(character["markers"]) as fh:
            markers = json.load(fh)
        markers = markers.get("markers", markers)
        bad = [n for n, v in markers.items() if not 0 <= int(v) < rig.n_vertices]
        if bad:
            raise InputError(f"markers {bad} index vertices outside the rig", path=character["markers"])
        rig = rig.with_markers(list(markers), list(markers.values()))
    identity_folder = ict_dir() if character["rig"] == "ict" else None
    out = make_character(rig, character.get("kind", "template"), seed=0, identity_folder=identity_folder)
    out.name = name
    write_rig_npz(out_rig, out)
    print(f"character {out.name}: {out.n_vertices} vertices, {out.n_shapes} shapes, {len(out.marker_names)} markers")
    return out
