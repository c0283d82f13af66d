"""Initial extrinsics: a pose graph over cameras linked by board views they share.

Every camera ``c`` has, from its own intrinsic calibration, the board-to-camera pose ``T_cv`` of each view
``v`` it saw (``x_c = R_cv p + t_cv``). Two cameras that saw the same view (same instant) give one
estimate of their relative pose ``T_ba = T_bv T_av^-1``; all shared views of an edge are averaged
(chordal L2 mean of rotations, per-axis median of translations, robust to a bad view). The world frame
is the reference camera's frame; the other cameras are chained from it along a maximum spanning tree
whose edge weight is the number of shared views (the best-supported relative poses are used first).
Cameras not connected to the reference camera are reported, not guessed. Board poses in the world are
then the chordal/mean average over the cameras that saw them.

Symmetric boards: a plain chessboard looks the same turned by 180 degrees, so two cameras may number its
corners in opposite orders. With ``symmetry`` (the board-frame transform mapping corner i to corner
N-1-i), every shared view offers two relative-pose candidates; the consensus candidate (the one most
views agree with within 10 degrees) wins, and each (camera, view) whose labelling disagrees with the
world board pose is reported in ``PoseGraph.flipped`` so the caller can renumber its corners.
ChArUco boards are not symmetric (``symmetry=None``).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from rigbuild.calibrate.rotations import chordal_mean

Pose = tuple[np.ndarray, np.ndarray]  # (R (3, 3), t (3,)): x_dst = R x_src + t


def invert(R: np.ndarray, t: np.ndarray) -> Pose:
    """Inverse of ``x -> R x + t``."""
    return R.T, -R.T @ t


def compose(A: Pose, B: Pose) -> Pose:
    """``A o B``: first B, then A."""
    return A[0] @ B[0], A[0] @ B[1] + A[1]


@dataclass
class PoseGraph:
    """Initial rig extrinsics.

    cameras : camera id -> world-to-camera pose (R, t); only cameras connected to the reference.
    boards : view key -> board-to-world pose (R, t); views seen by at least one connected camera.
    reference : the camera whose frame is the world frame.
    unreachable : cameras sharing no chain of board views with the reference camera.
    edges : (parent, child, n_shared_views) of the spanning tree used.
    """

    cameras: dict[str, Pose]
    boards: dict[str, Pose]
    reference: str
    unreachable: list[str] = field(default_factory=list)
    edges: list[tuple[str, str, int]] = field(default_factory=list)
    flipped: dict[str, list[str]] = field(default_factory=dict)


def average_poses(poses: list[Pose]) -> Pose:
    """Robust average of poses: chordal mean rotation, per-axis median translation."""
    R = chordal_mean(np.stack([p[0] for p in poses]))
    t = np.median(np.stack([p[1] for p in poses]), axis=0)
    return R, t


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def consensus(candidates: list[list[Pose]], tol_deg: float = 10.0) -> tuple[list[int], list[Pose]]:
    """Pick one candidate per item so that the picks agree: (chosen index per item, chosen poses).

    candidates : per item, 1 or 2 pose hypotheses. The hypothesis that the most items have a candidate
    within ``tol_deg`` of (rotation) is the anchor; each item takes its candidate nearest the anchor.
    """
    flat = [c for cands in candidates for c in cands]
    best, best_score = flat[0], -1
    for h in flat:
        score = sum(min(_angle_deg(h[0], c[0]) for c in cands) < tol_deg for cands in candidates)
        if score > best_score:
            best, best_score = h, score
    idx = [int(np.argmin([_angle_deg(best[0], c[0]) for c in cands])) for cands in candidates]
    return idx, [cands[i] for cands, i in zip(candidates, idx)]


def relative_pose(views_a: Mapping[str, Pose], views_b: Mapping[str, Pose],
                  symmetry: Pose | None = None) -> tuple[Pose, int]:
    """Pose of camera b relative to camera a (``x_b = R x_a + t``) from their shared views; (pose, n)."""
    shared = sorted(set(views_a) & set(views_b))
    if not shared:
        return (np.eye(3), np.zeros(3)), 0
    cands = []
    for v in shared:
        a_inv = invert(*views_a[v])
        c = [compose(views_b[v], a_inv)]
        if symmetry is not None:
            c.append(compose(compose(views_b[v], symmetry), a_inv))
        cands.append(c)
    _, ests = consensus(cands)
    return average_poses(ests), len(shared)


def build_pose_graph(view_poses: Mapping[str, Mapping[str, Pose]], reference: str,
                     symmetry: Pose | None = None) -> PoseGraph:
    """Chain camera poses through shared board views.

    view_poses : camera id -> view key -> board-to-camera pose (R (3, 3), t (3,) mm).
    reference : camera id that defines the world frame (R = I, t = 0).
    symmetry : board-frame pose of the board's 180-degree symmetry (chessboards), or None.
    """
    cams = list(view_poses)
    if reference not in view_poses:
        raise KeyError(f"reference camera '{reference}' has no board views")
    shared = {}
    for i, a in enumerate(cams):
        for b in cams[i + 1:]:
            n = len(set(view_poses[a]) & set(view_poses[b]))
            if n:
                shared.setdefault(a, {})[b] = n
                shared.setdefault(b, {})[a] = n
    # Prim's maximum spanning tree from the reference camera
    world: dict[str, Pose] = {reference: (np.eye(3), np.zeros(3))}
    edges: list[tuple[str, str, int]] = []
    heap: list[tuple[int, str, str]] = [(-n, reference, b) for b, n in shared.get(reference, {}).items()]
    heapq.heapify(heap)
    while heap:
        negn, parent, child = heapq.heappop(heap)
        if child in world:
            continue
        rel, n = relative_pose(view_poses[parent], view_poses[child], symmetry)
        world[child] = compose(rel, world[parent])
        edges.append((parent, child, n))
        for b, m in shared.get(child, {}).items():
            if b not in world:
                heapq.heappush(heap, (-m, child, b))
    unreachable = [c for c in cams if c not in world]
    boards: dict[str, Pose] = {}
    per_view: dict[str, list[list[Pose]]] = {}
    seen_by: dict[str, list[str]] = {}
    for c in world:
        cam_to_world = invert(*world[c])
        for v, pose in view_poses[c].items():
            w = compose(cam_to_world, pose)
            per_view.setdefault(v, []).append([w] if symmetry is None else [w, compose(w, symmetry)])
            seen_by.setdefault(v, []).append(c)
    flipped: dict[str, list[str]] = {}
    for v, cands in per_view.items():
        idx, ests = consensus(cands)
        for c, i in zip(seen_by[v], idx):
            if i == 1:
                flipped.setdefault(c, []).append(v)
        R = chordal_mean(np.stack([e[0] for e in ests]))
        t = np.mean(np.stack([e[1] for e in ests]), axis=0) if len(ests) < 3 else np.median(
            np.stack([e[1] for e in ests]), axis=0)
        boards[v] = (R, t)
    return PoseGraph(world, boards, reference, unreachable, edges, flipped)
