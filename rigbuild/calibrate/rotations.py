"""Vectorized rotation helpers: Rodrigues vectors <-> matrices, chordal mean of rotations."""

from __future__ import annotations

import numpy as np


def rodrigues(rvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from Rodrigues vectors (..., 3) (angle = norm, radians)."""
    r = np.asarray(rvecs, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    k = r / th[..., None]
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    Kx = np.stack([np.stack([zero, -kz, ky], -1), np.stack([kz, zero, -kx], -1), np.stack([-ky, kx, zero], -1)], -2)
    s = np.where(small, 0.0, np.sin(theta))[..., None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(theta))[..., None, None]
    # small angles: first-order R = I + [r]x
    rx = np.stack([np.stack([zero, -r[..., 2], r[..., 1]], -1), np.stack([r[..., 2], zero, -r[..., 0]], -1),
                   np.stack([-r[..., 1], r[..., 0], zero], -1)], -2)
    eye = np.broadcast_to(np.eye(3), Kx.shape)
    full = eye + s * Kx + c * (Kx @ Kx)
    return np.where(small[..., None, None], eye + rx, full)


def rotation_to_rvec(R: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (..., 3) of rotation matrices (..., 3, 3) (exact log map, any angle)."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 3))
    for i, Ri in enumerate(flat):
        c = np.clip((np.trace(Ri) - 1.0) / 2.0, -1.0, 1.0)
        w = np.array([Ri[2, 1] - Ri[1, 2], Ri[0, 2] - Ri[2, 0], Ri[1, 0] - Ri[0, 1]]) / 2.0
        s = np.linalg.norm(w)
        theta = np.arctan2(s, c)
        if s > 1e-7:
            out[i] = w / s * theta
        elif c > 0:  # near identity
            out[i] = w
        else:  # near 180 degrees: axis from the symmetric part
            B = (Ri + np.eye(3)) / 2.0
            axis = B[np.argmax(np.diag(B))]
            axis = axis / np.linalg.norm(axis)
            out[i] = axis * theta
    return out.reshape(R.shape[:-2] + (3,))


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to a (3, 3) matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def chordal_mean(Rs: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """L2 chordal mean (3, 3) of rotations (N, 3, 3), optionally weighted (N,)."""
    Rs = np.asarray(Rs, dtype=np.float64)
    w = np.ones(len(Rs)) if weights is None else np.asarray(weights, dtype=np.float64)
    return project_to_rotation(np.einsum("n,nij->ij", w, Rs))
