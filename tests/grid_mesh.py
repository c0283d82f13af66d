"""A tiny triangulated grid for the tracking tests (analytic cases)."""

from __future__ import annotations

import numpy as np


def grid_mesh(n: int = 6, size: float = 10.0, bump: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A (n x n) vertex grid in the z=0 plane (mm), split into triangles; optional smooth bump in z.
    Returns vertices (n*n, 3) and faces (2 (n-1)^2, 3)."""
    xs = np.linspace(0, size, n)
    X, Y = np.meshgrid(xs, xs)
    Z = bump * np.sin(X / size * np.pi) * np.sin(Y / size * np.pi)
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    F = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            F += [[a, b, e], [a, e, d]]
    return V, np.array(F)
