"""Report figures of the personalization: the EM convergence curve and per-shape change heat maps
(like Ma et al. 2016, figure 3: the initial shape and the personalized shape coloured by the
magnitude of the change)."""

from __future__ import annotations

import os

import numpy as np

from rigbuild.io.atomic import atomic_path


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_convergence(objective: list[dict], path: str | os.PathLike) -> None:
    """Objective (total and each term) and RMS residual per EM step -> PNG."""
    plt = _plt()
    x = np.arange(len(objective))
    labels = [f"{o['iteration']}{o['step'][0]}" for o in objective]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for key in ("total", "E_g"):
        ax[0].semilogy(x, [max(o[key], 1e-12) for o in objective], marker="o", label=key)
    for key, lam in (("E_r", "lambda_r"), ("E_d", "lambda_d"), ("E_s", "lambda_s"), ("E_t", "lambda_t")):
        vals = [o.get(key, 0.0) * o.get(lam, 1.0) for o in objective]
        if max(vals) > 0:
            ax[0].semilogy(x, np.maximum(vals, 1e-12), marker=".", label=f"{lam} {key}")
    ax[0].set_ylim(bottom=1e-4 * min(o["total"] for o in objective))
    ax[0].set_title("EM objective (w = weights step, s = shapes step)")
    ax[0].set_xticks(x, labels, fontsize=7)
    ax[0].legend(fontsize=7)
    ax[1].plot(x, [o["rms_mm"] for o in objective], marker="o", label="confidence-weighted")
    ax[1].plot(x, [o["rms_unweighted_mm"] for o in objective], marker=".", label="unweighted")
    ax[1].legend(fontsize=7)
    ax[1].set_title("fit residual RMS (mm)")
    ax[1].set_xticks(x, labels, fontsize=7)
    ax[1].grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _draw(ax, verts: np.ndarray, faces: np.ndarray, values: np.ndarray | None, vmax: float, cmap) -> None:
    """Front view (x, y), painter's order by depth z; Lambert grey, or colour = per-vertex values."""
    from matplotlib.collections import PolyCollection

    tri = verts[faces]
    order = np.argsort(tri[:, :, 2].mean(1))
    tri = tri[order]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    shade = 0.35 + 0.65 * np.clip(n @ np.array([0.3, 0.3, 0.9]) / np.linalg.norm([0.3, 0.3, 0.9]), 0, 1)
    if values is None:
        colours = np.repeat(shade[:, None], 3, 1)
    else:
        v = values[faces[order]].mean(1)
        colours = cmap(np.clip(v / max(vmax, 1e-12), 0, 1))[:, :3] * shade[:, None]
    ax.add_collection(PolyCollection(tri[:, :, :2], facecolors=colours, edgecolors="none"))
    ax.set_xlim(verts[:, 0].min(), verts[:, 0].max())
    ax.set_ylim(verts[:, 1].min(), verts[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")


def region_faces(faces: np.ndarray, vertices: np.ndarray | None) -> np.ndarray:
    """Triangles whose three corners are in ``vertices`` (all triangles when None)."""
    if vertices is None:
        return faces
    sel = np.zeros(int(faces.max()) + 1, dtype=bool)
    sel[vertices[vertices <= faces.max()]] = True
    return faces[sel[faces].all(1)]


def render_change_heatmap(neutral: np.ndarray, initial_delta: np.ndarray, delta: np.ndarray, faces: np.ndarray,
                          path: str | os.PathLike, title: str = "", region: np.ndarray | None = None,
                          vmax: float | None = None) -> float:
    """Two panels: the initial shape (``neutral + initial_delta``, grey) and the personalized shape
    (``neutral + delta``) coloured by ``|delta - initial_delta|`` per vertex (mm). Returns the max change."""
    plt = _plt()
    change = np.linalg.norm(delta - initial_delta, axis=1)
    f = region_faces(faces, region)
    vmax = float(change[np.unique(f)].max()) if vmax is None else vmax
    cmap = plt.get_cmap("inferno")
    fig, ax = plt.subplots(1, 2, figsize=(7, 4.2))
    _draw(ax[0], neutral + initial_delta, f, None, vmax, cmap)
    ax[0].set_title("initial (D*)", fontsize=9)
    _draw(ax[1], neutral + delta, f, change, vmax, cmap)
    ax[1].set_title("personalized, |D - D*|", fontsize=9)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=ax[1], fraction=0.046, pad=0.02, label="mm")
    fig.suptitle(title, fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return float(change.max())


def render_change_overview(neutral: np.ndarray, initial: np.ndarray, deltas: np.ndarray, faces: np.ndarray,
                           names: list[str], path: str | os.PathLike, region: np.ndarray | None = None,
                           n: int = 6) -> list[str]:
    """Figure-3-like grid: the ``n`` most-changed shapes, initial (top) and personalized coloured by
    the change (bottom), one shared colour scale. Returns the names shown."""
    plt = _plt()
    f = region_faces(faces, region)
    vs = np.unique(f)
    change = np.linalg.norm(deltas - initial, axis=2)
    rms = np.sqrt((change[:, vs] ** 2).mean(1))
    pick = np.argsort(-rms)[:n]
    vmax = float(change[np.ix_(pick, vs)].max()) if pick.size else 1.0
    cmap = plt.get_cmap("inferno")
    fig, ax = plt.subplots(2, max(len(pick), 1), figsize=(2.6 * max(len(pick), 1), 5.6), squeeze=False)
    for c, k in enumerate(pick):
        _draw(ax[0, c], neutral + initial[k], f, None, vmax, cmap)
        ax[0, c].set_title(names[k], fontsize=8)
        _draw(ax[1, c], neutral + deltas[k], f, change[k], vmax, cmap)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=ax[1, :].tolist(), fraction=0.02, pad=0.01, label="|D - D*| (mm)")
    fig.suptitle("initial shapes (top) and personalized shapes coloured by the change (bottom)", fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return [names[k] for k in pick]
