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


def write_tracked_session(root, template: Rig, actor_deltas: np.ndarray, weights: np.ndarray,
                          sequence_ids: np.ndarray, frames: np.ndarray, world=None, cameras=None) -> dict:
    """A small session on disk for the personalize stage and its evaluation, under ``root``.

    Writes ``session/ground_truth/actor_rig.npz`` and ``ground_truth/rom/rom<s>.npz`` (vertices, weights,
    shape_names, frames) as :mod:`rigbuild.synth.session` does, and the tracked sequences
    ``results/track/rom<s>/vertices.npz`` (the ground-truth meshes, confidence 1). ``world`` (R, t): the tracked
    meshes are in a calibrated world ``x_cal = R x_gt + t``; with ``cameras`` (a list of Camera in the
    ground-truth world) ``ground_truth/cameras.json`` and ``results/calib/cameras.json`` (the same cameras in
    the calibrated world) are written too. Returns dict(session, gt, tracks {name: path}, cameras or None)."""
    from rigbuild.io.atomic import save_npz
    from rigbuild.io.rigs import write_rig_npz

    R, t = world if world is not None else (np.eye(3), np.zeros(3))
    sess = root / "session"
    gt = sess / "ground_truth"
    write_rig_npz(gt / "actor_rig.npz", Rig(template.neutral, actor_deltas, template.shape_names, template.faces,
                                            face_region=template.face_region, name="actor"))
    tracks = {}
    for s in np.unique(sequence_ids):
        name = f"rom{s:02d}"
        sel = sequence_ids == s
        fr = np.arange(sel.sum())
        save_npz(gt / "rom" / f"{name}.npz", vertices=frames[sel].astype(np.float32),
                 weights=weights[sel].astype(np.float32), shape_names=np.asarray(template.shape_names), frames=fr)
        p = root / "results" / "track" / name / "vertices.npz"
        save_npz(p, vertices=(frames[sel] @ R.T + t).astype(np.float32),
                 confidence=np.ones(frames[sel].shape[:2], np.float32), frames=fr)
        tracks[name] = p
    calibrated = None
    if cameras is not None:
        from dataclasses import replace

        from rigbuild.io.cameras import write_cameras

        write_cameras(gt / "cameras.json", cameras)
        # x_cam = Rc x_gt + tc = Rc R^T (x_cal - t) + tc
        calibrated = root / "results" / "calib" / "cameras.json"
        write_cameras(calibrated, [replace(c, R=c.R @ R.T, t=c.t - c.R @ R.T @ t) for c in cameras])
    return dict(session=sess, gt=gt, tracks=tracks, cameras=calibrated)
