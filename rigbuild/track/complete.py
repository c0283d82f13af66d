"""The whole production mesh from a tracked face: parts no camera sees (teeth, gums, tongue, eyeballs, lashes,
the parts of other mesh components) posed by the template's own blendshapes.

The tracker solves the connected skin (face, head, mouth and eye sockets); the other components of a production
mesh are not seen well enough to track. Attached to their nearest tracked vertices they follow the wrong part
(the lower teeth the upper lip, an eyeball its blinking lid). Here each tracked frame is explained by the template's
expression shapes under a rigid head motion, ``x = R (b + D w) + t`` over the face region (bounded weights in
[0, 1], a few alternations of weighted least squares and Kabsch), and the untracked vertices take that pose: the
jaw's parts follow the fitted jaw shapes, the eyeballs and the rest of the head the head motion.
"""

from __future__ import annotations

import numpy as np

from rigbuild.geometry.rigid import apply_rigid, fit_rigid_motion


def shapes_in_world(deltas: np.ndarray, similarity: tuple[float, np.ndarray, np.ndarray]) -> np.ndarray:
    """Template deltas (K, V, 3) mm turned and scaled into the world of a registered neutral: ``s R d``
    (``similarity`` = (s, R (3, 3), t) template -> world, the neutral registration's)."""
    s, R, _ = similarity
    return float(s) * np.einsum("kvc,dc->kvd", np.asarray(deltas, np.float64), np.asarray(R, np.float64))


def bounded_weights(gram_chol: np.ndarray, rhs: np.ndarray, upper: float = 1.0) -> np.ndarray:
    """``argmin_w ||D w - y||^2`` subject to ``0 <= w <= upper`` from the Cholesky factor ``L`` (K, K) of
    ``D^T D`` and ``D^T y`` (K,): the least-squares problem ``||L^T w - L^-1 D^T y||``."""
    from scipy.linalg import solve_triangular
    from scipy.optimize import lsq_linear

    z = solve_triangular(gram_chol, rhs, lower=True)
    return lsq_linear(gram_chol.T, z, bounds=(0.0, upper), method="bvls").x


def fit_expression_and_head(neutral: np.ndarray, deltas: np.ndarray, frames: np.ndarray, iterations: int = 4
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights and rigid head motion explaining tracked frames by a blendshape model, ``x_i ~ R_i (b + D w_i) + t_i``.

    neutral (N, 3) mm, deltas (K, N, 3) mm (in the neutral's frame), frames (F, N, 3) mm, all on the same N
    vertices (the face region). Weights in [0, 1]; alternation of the bounded weight solve and Kabsch, starting
    from the rigid fit of the neutral. Returns weights (F, K), rotations (F, 3, 3), translations (F, 3) mm.
    """
    b = np.asarray(neutral, np.float64)
    D = np.asarray(deltas, np.float64).reshape(deltas.shape[0], -1).T  # (3N, K)
    X = np.asarray(frames, np.float64)
    F, K = X.shape[0], D.shape[1]
    gram = D.T @ D + 1e-9 * np.trace(D.T @ D) / max(K, 1) * np.eye(K)
    L = np.linalg.cholesky(gram)
    W = np.zeros((F, K))
    Rs = np.repeat(np.eye(3)[None], F, 0)
    ts = np.zeros((F, 3))
    for i in range(F):
        model = b
        for _ in range(max(int(iterations), 1)):
            R, t = fit_rigid_motion(model, X[i])
            y = ((X[i] - t) @ R - b).ravel()  # the frame in the rig's frame, minus the neutral
            W[i] = bounded_weights(L, D.T @ y)
            model = b + (D @ W[i]).reshape(-1, 3)
        Rs[i], ts[i] = fit_rigid_motion(model, X[i])
    return W, Rs, ts


def complete_untracked(tracked_full: np.ndarray, neutral: np.ndarray, deltas: np.ndarray, fit_vertices: np.ndarray,
                       untracked: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Pose the untracked vertices of tracked full meshes by the template's shapes.

    tracked_full (F, V, 3) mm: the tracked frames (full topology; the untracked rows are overwritten);
    neutral (V, 3) mm: the registered neutral; deltas (K, V, 3) mm: the template's shapes in the neutral's world
    (:func:`shapes_in_world`); fit_vertices (N,): the tracked vertices the pose is fitted on (the face region);
    untracked (U,): the vertices to pose. Returns a copy of ``tracked_full`` with the untracked rows posed
    ``R_i (b + D w_i) + t_i``.
    """
    out = np.array(tracked_full, np.float64, copy=True)
    untracked = np.asarray(untracked, np.int64)
    if untracked.size == 0 or deltas.shape[0] == 0:
        return out
    fit_vertices = np.asarray(fit_vertices, np.int64)
    W, Rs, ts = fit_expression_and_head(neutral[fit_vertices], deltas[:, fit_vertices], out[:, fit_vertices],
                                        iterations)
    posed = neutral[untracked][None] + np.einsum("fk,kuc->fuc", W, deltas[:, untracked], optimize=True)
    for i in range(out.shape[0]):
        out[i, untracked] = apply_rigid(posed[i], Rs[i], ts[i])
    return out
