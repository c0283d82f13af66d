"""Synthetic personalization scenes: a template, a perturbed ground-truth actor and ROM frames.

Frames are made the way :mod:`rigbuild.synth.session` makes ``ground_truth/rom/<seq>.npz``: ROM weights
(:func:`rigbuild.synth.motion.make_rom_weights`), the actor's rig evaluated, rigid head motion about
the face centre. Shared by tests/test_personalize_*.py and benchmarks/bench_personalize.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigbuild.rig import Rig


@dataclass
class RomScene:
    template: Rig
    actor: Rig
    info: dict
    vertices: np.ndarray  # (F, V, 3) world mm
    weights: np.ndarray  # (F, K) ground truth
    rotations: np.ndarray  # (F, 3, 3)
    translations: np.ndarray  # (F, 3)
    sequence_ids: np.ndarray  # (F,)


def make_rom_scene(template: Rig, n_sequences: int = 8, frames_per_sequence: int = 10, seed: int = 0,
                   identity_folder=None, max_rotation_deg: float = 2.0, max_translation_mm: float = 3.0,
                   actor_kwargs: dict | None = None, peak_range: tuple[float, float] = (1.0, 1.0)) -> RomScene:
    from rigbuild.synth.actor import make_actor_rig
    from rigbuild.synth.motion import make_head_motion, make_rom_weights

    actor, info = make_actor_rig(template, seed=seed, identity_folder=identity_folder, **(actor_kwargs or {}))
    seqs = make_rom_weights(actor.shape_names, n_sequences, frames_per_sequence, seed=seed + 2, peak_range=peak_range)
    centre = actor.neutral[actor.face_vertices].mean(0)
    verts, Ws, Rs, ts, ids = [], [], [], [], []
    for s, W in enumerate(seqs):
        R, t = make_head_motion(W.shape[0], seed=seed + 100 + s, max_rotation_deg=max_rotation_deg,
                                max_translation_mm=max_translation_mm)
        tw = centre[None] - np.einsum("fij,j->fi", R, centre) + t
        v = np.einsum("fij,fvj->fvi", R, actor.evaluate(W)) + tw[:, None, :]
        verts.append(v)
        Ws.append(W)
        Rs.append(R)
        ts.append(tw)
        ids.append(np.full(W.shape[0], s))
    return RomScene(template, actor, info, np.concatenate(verts), np.concatenate(Ws), np.concatenate(Rs),
                    np.concatenate(ts), np.concatenate(ids))
