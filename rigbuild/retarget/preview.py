"""Preview images for the report: actor markers beside the retargeted character, a few frames."""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from rigbuild.io.atomic import atomic_path
from rigbuild.rig import Rig


def _face_triangles(rig: Rig) -> np.ndarray:
    fv = np.zeros(rig.n_vertices, bool)
    fv[rig.face_vertices] = True
    return rig.faces[fv[rig.faces].all(1)]


def shaded_front_view(ax, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Draw a mesh (V, 3) seen from +z (orthographic, painter's order, Lambert shading) on a matplotlib axis."""
    from matplotlib.collections import PolyCollection

    tri = vertices[triangles]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    front = n[:, 2] > 0
    light = np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    shade = np.clip(n[front] @ light, 0, 1) * 0.8 + 0.15
    order = np.argsort(tri[front, :, 2].mean(1))
    polys = tri[front][order][:, :, :2]
    colors = np.repeat(shade[order, None], 3, axis=1) * np.array([1.0, 0.85, 0.75])
    ax.add_collection(PolyCollection(polys, facecolors=colors, edgecolors="none"))
    ax.set_xlim(vertices[:, 0].min(), vertices[:, 0].max())
    ax.set_ylim(vertices[:, 1].min(), vertices[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")


def write_preview(
    path: str | os.PathLike,
    actor_markers: np.ndarray,
    actor_neutral: np.ndarray,
    character: Rig,
    weights: np.ndarray,
    frames: Sequence[int],
    fps: float,
    title: str = "",
) -> None:
    """PNG with one row per frame: stabilized actor markers (grey neutral, blue frame) | character mesh.

    actor_markers (F, M, 3) stabilized mm (NaN gaps); actor_neutral (M, 3); weights (F, K) for ``character``.
    Actor markers are drawn in the plane of their two principal axes (front view for any capture frame).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    c = actor_neutral.mean(0)
    _, _, Vt = np.linalg.svd(actor_neutral - c, full_matrices=False)
    basis = Vt[:2].T
    if basis[0, 0] < 0:
        basis[:, 0] *= -1
    if basis[1, 1] < 0:
        basis[:, 1] *= -1  # keep "up" up for y-up captures
    tris = _face_triangles(character)
    fig, axes = plt.subplots(len(frames), 2, figsize=(6, 3 * len(frames)), squeeze=False)
    for row, f in enumerate(frames):
        a = axes[row, 0]
        p0 = (actor_neutral - c) @ basis
        p = (actor_markers[f] - c) @ basis
        a.scatter(p0[:, 0], p0[:, 1], s=6, c="0.7")
        a.scatter(p[:, 0], p[:, 1], s=10, c="tab:blue")
        a.set_aspect("equal")
        a.axis("off")
        a.set_title(f"actor, frame {f} ({f / fps:.2f} s)", fontsize=8)
        shaded_front_view(axes[row, 1], character.evaluate(weights[f]), tris)
        axes[row, 1].set_title(f"{character.name}", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
