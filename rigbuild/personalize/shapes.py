"""Blendshape update (Ma et al. 2016, eq. 5-7) with the neutral update (the extra column of W-hat).

With the weights ``w_i`` and rigid motions fixed, the shapes minimize

    E = sum_i || M_i ((D-hat) w-hat_i - p~_i) ||^2 + lambda_r E_r + lambda_d E_d

where ``D-hat = [d_0, D]`` (the neutral update ``d_0`` and the K pose offsets), ``w-hat_i = [1, w_i]``
(so a constant bias goes into the neutral, not the shapes), ``p~_i = R_i^T (p_i - t_i) - b_0`` the
tracked frame in the rig's frame minus the neutral, ``M_i`` the per-vertex confidence,

    E_r = sum_j || G (b_0 + D-hat_j) - g-hat*_j ||^2 = sum_j || G (D-hat_j - D-hat*_j) ||^2
    E_d = || D-hat - D-hat* ||^2,    D-hat* = [0, D*],  g-hat* = [identity, g*]

(``G`` the per-triangle gradient operator on the neutral, :mod:`rigbuild.geometry.deformation_transfer`;
``g*_k = G (b_0 + D*_k)`` are the initial shapes' deformation gradients (the in-plane part of their
4th-vertex gradients, the only part vertex positions can reach) and the neutral's are the identity, so
``G b_0`` cancels), and the local support ``D_kv = 0`` wherever ``D*_kv = 0``.

The unknowns are ``X_j = D-hat_j - D-hat*_j`` on each column's support inside the active vertex set
(the neutral column is free on every active vertex). The energy is the same quadratic for x, y and z:
one sparse SPD system, three right-hand sides. ``G^T G``, the variable layout, the sparsity pattern and
CHOLMOD's symbolic analysis are built once; each EM iteration only refills the data block (it depends
on the weights) and re-factors numerically.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from rigbuild.geometry.deformation_transfer import gradient_operator
from rigbuild.geometry.sparse_cholesky import SparseCholesky


class ShapeUpdate:
    """Prefactored structure of the shape update on the active vertices.

    Parameters
    ----------
    neutral : (V, 3) the actor's neutral ``b_0`` (mm; reference of ``G``).
    initial_deltas : (K, V, 3) ``D*`` (mm), already zero outside each shape's support.
    faces : (F, 3) triangles.
    active : (A,) vertex ids that are unknowns (the rest keep ``D*`` and a zero neutral update).
    lambda_r, lambda_d : weights of ``E_r`` and ``E_d``.
    update_neutral : include the neutral column ``d_0`` (default True).
    support : (K, V) bool, where each shape may move (default: ``D*_kv != 0``).
    """

    def __init__(self, neutral: np.ndarray, initial_deltas: np.ndarray, faces: np.ndarray, active: np.ndarray,
                 lambda_r: float = 0.1, lambda_d: float = 0.05, update_neutral: bool = True,
                 support: np.ndarray | None = None):
        self.lambda_r = float(lambda_r)
        self.lambda_d = float(lambda_d)
        self.update_neutral = bool(update_neutral)
        self.active = np.asarray(active, dtype=np.int64)
        K, V, _ = initial_deltas.shape
        self.K = K
        A = self.active.size
        self.n_active = A
        if support is None:
            support = np.any(initial_deltas != 0, axis=2)
        sup_a = np.asarray(support, bool)[:, self.active]  # (K, A)
        ncol = K + 1
        mask = np.zeros((ncol, A), dtype=bool)
        mask[0] = self.update_neutral
        mask[1:] = sup_a
        self.mask = mask
        counts = mask.sum(1)
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.n_vars = int(self.offsets[-1])
        var_of = np.full((ncol, A), -1, dtype=np.int64)
        for j in range(ncol):
            var_of[j, mask[j]] = self.offsets[j] + np.arange(counts[j])
        self.var_of = var_of

        G = gradient_operator(neutral, faces)
        self.G_active = G[:, self.active].tocsr()
        GtG = (self.G_active.T @ self.G_active).tocsr()

        # --- data block pattern: for each vertex, all pairs of columns whose support holds it
        pj, pl = np.tril_indices(ncol)
        self.pair_j, self.pair_l = pj, pl
        rows, cols, pair_id, vert = [], [], [], []
        for p, (j, l) in enumerate(zip(pj, pl)):
            both = np.flatnonzero(mask[j] & mask[l])
            if both.size == 0:
                continue
            rows.append(var_of[j, both])
            cols.append(var_of[l, both])
            pair_id.append(np.full(both.size, p, dtype=np.int64))
            vert.append(both)
        d_rows = np.concatenate(rows)
        d_cols = np.concatenate(cols)
        d_pair = np.concatenate(pair_id)
        d_vert = np.concatenate(vert)
        order = np.argsort(d_vert, kind="stable")  # chunked evaluation by vertex
        self._d_rows, self._d_cols = d_rows[order], d_cols[order]
        self._d_pair, self._d_vert = d_pair[order], d_vert[order]

        # --- constant part: lambda_r G^T G per column on its support + lambda_d I
        c_rows, c_cols, c_vals = [], [], []
        for j in range(ncol):
            idx = np.flatnonzero(mask[j])
            if idx.size == 0:
                continue
            sub = sp.tril(GtG[idx][:, idx], format="coo")
            c_rows.append(var_of[j, idx[sub.row]])
            c_cols.append(var_of[j, idx[sub.col]])
            c_vals.append(self.lambda_r * sub.data)
        diag = np.arange(self.n_vars)
        c_rows.append(diag)
        c_cols.append(diag)
        c_vals.append(np.full(self.n_vars, self.lambda_d))
        c_rows = np.concatenate(c_rows)
        c_cols = np.concatenate(c_cols)
        c_vals = np.concatenate(c_vals)

        keys = np.concatenate([self._d_rows * self.n_vars + self._d_cols, c_rows * self.n_vars + c_cols])
        uniq, inv = np.unique(keys, return_inverse=True)
        self._pat_rows = uniq // self.n_vars
        self._pat_cols = uniq % self.n_vars
        self.nnz = int(uniq.size)
        nd = self._d_rows.size
        self._inv_data = inv[:nd]
        self._const = np.bincount(inv[nd:], weights=c_vals, minlength=self.nnz)
        self._factor: SparseCholesky | None = None

    # ------------------------------------------------------------------ assembly
    def _data_values(self, W_hat: np.ndarray, conf2: np.ndarray, chunk: int = 2048) -> np.ndarray:
        """Data-block entries ``sum_i m2_iv W_ij W_il`` at the pattern's data positions."""
        WW = W_hat[:, self.pair_j] * W_hat[:, self.pair_l]  # (F, P)
        vals = np.empty(self._d_rows.size)
        uniform = np.all(conf2 == conf2[:1], axis=0).all()
        if uniform:
            base = WW.sum(0)  # conf2 equal across frames: m2_v * (W^T W)_jl
            return conf2[0, self._d_vert] * base[self._d_pair]
        starts = np.searchsorted(self._d_vert, np.arange(0, self.n_active + chunk, chunk))
        for c0 in range(0, self.n_active, chunk):
            c1 = min(c0 + chunk, self.n_active)
            s, e = starts[c0 // chunk], starts[c0 // chunk + 1]
            C = conf2[:, c0:c1].T @ WW  # (chunk, P)
            vals[s:e] = C[self._d_vert[s:e] - c0, self._d_pair[s:e]]
        return vals

    def matrix_values(self, W_hat: np.ndarray, conf2: np.ndarray) -> np.ndarray:
        """Values of the system matrix on the fixed lower-triangle pattern."""
        data = self._data_values(W_hat, conf2)
        return self._const + np.bincount(self._inv_data, weights=data, minlength=self.nnz)

    def factor(self, W_hat: np.ndarray, conf2: np.ndarray) -> None:
        """(Re)factor the system for weights W_hat (F, K+1) and confidences squared conf2 (F, A)."""
        trip = (self.matrix_values(W_hat, conf2), self._pat_rows, self._pat_cols, self.n_vars)
        if self._factor is None:
            self._factor = SparseCholesky(trip)
        else:
            self._factor.refactor(trip)

    def rhs(self, W_hat: np.ndarray, conf2: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """Right-hand sides (n_vars, 3): ``sum_i m2_iv W_ij residual_iv`` at each variable.

        residual : (F, A, 3) ``p~_i - D* w_i`` on the active vertices (mm).
        """
        B = np.einsum("ia,iac,ij->jac", conf2, residual, W_hat, optimize=True)  # (K+1, A, 3)
        out = np.empty((self.n_vars, 3))
        for j in range(self.K + 1):
            idx = self.mask[j]
            out[self.offsets[j]:self.offsets[j + 1]] = B[j, idx]
        return out

    def solve(self, W_hat: np.ndarray, conf2: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """Minimize the shape energy. W_hat (F, K+1) = [1, w_i]; conf2 (F, A) squared confidences;
        residual (F, A, 3) mm. Returns X (K+1, A, 3): the change of [neutral, shapes] from [0, D*]."""
        self.factor(W_hat, conf2)
        sol = self._factor.solve(self.rhs(W_hat, conf2, residual))
        X = np.zeros((self.K + 1, self.n_active, 3))
        for j in range(self.K + 1):
            X[j, self.mask[j]] = sol[self.offsets[j]:self.offsets[j + 1]]
        return X

    # ------------------------------------------------------------------ energies
    def regularizers(self, X: np.ndarray) -> tuple[float, float]:
        """``(E_r, E_d)`` (unweighted) of a change X (K+1, A, 3) from [0, D*]."""
        Er = 0.0
        for j in range(X.shape[0]):
            g = self.G_active @ X[j]
            Er += float((g * g).sum())
        return Er, float((X * X).sum())
