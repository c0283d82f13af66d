"""Sparse symmetric positive-definite solves with CHOLMOD (the copy bundled with cvxopt).

cvxopt's CHOLMOD is about 10x faster than scipy's ``splu`` on mesh-Laplacian-like systems
(/work/shared/notes/stack.md). The symbolic analysis (fill-reducing ordering, elimination tree)
is kept so that a matrix with the same sparsity pattern can be re-factored cheaply.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from rigbuild.errors import RigbuildError


def _to_cvxopt_lower(A):
    """A scipy sparse matrix (its lower triangle is taken) or a lower-triangle triplet
    ``(values, rows, cols, n)`` with ``rows >= cols`` -> cvxopt spmatrix."""
    import cvxopt

    if isinstance(A, tuple):
        vals, rows, cols, n = A
        return cvxopt.spmatrix(np.asarray(vals, np.float64), np.asarray(rows, np.int64),
                               np.asarray(cols, np.int64), size=(int(n), int(n)))
    L = sp.tril(sp.csc_matrix(A), format="coo")
    return cvxopt.spmatrix(
        L.data.astype(np.float64), L.row.astype(np.int64), L.col.astype(np.int64), size=L.shape
    )


class SparseCholesky:
    """Cholesky factor of a sparse SPD matrix ``A`` (n, n); only its lower triangle is read.

    ``A`` is a scipy sparse matrix or a lower-triangle triplet ``(values, rows, cols, n)``.
    ``solve(B)`` solves ``A X = B`` for B (n,) or (n, m) (all m right-hand sides in one call).
    ``refactor(A_new)`` reuses the symbolic analysis for a matrix with the same sparsity pattern.
    """

    def __init__(self, A):
        import cvxopt.cholmod as cholmod

        self._cholmod = cholmod
        Ac = _to_cvxopt_lower(A)
        self.n = int(Ac.size[0])
        if Ac.size[1] != self.n:
            raise ValueError(f"SparseCholesky: matrix must be square, got {Ac.size}")
        self._pattern_nnz = len(Ac.V)
        self._symbolic = cholmod.symbolic(Ac, uplo="L")
        self._numeric(Ac)

    def _numeric(self, Ac) -> None:
        try:
            self._cholmod.numeric(Ac, self._symbolic)
        except ArithmeticError as exc:
            raise RigbuildError(
                f"sparse system is not positive definite (CHOLMOD failed at column {exc.args[0]})"
            ) from None

    def refactor(self, A) -> None:
        """Numeric re-factorization of a matrix with the same sparsity pattern as the first one."""
        Ac = _to_cvxopt_lower(A)
        if len(Ac.V) != self._pattern_nnz:
            raise ValueError("SparseCholesky.refactor: sparsity pattern changed")
        self._numeric(Ac)

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Solve ``A X = B``; B (n,) or (n, m) float64. Returns an array of B's shape."""
        import cvxopt

        B = np.asarray(B, dtype=np.float64)
        vec = B.ndim == 1
        B2 = B.reshape(self.n, -1)
        X = cvxopt.matrix(np.asfortranarray(B2))
        self._cholmod.solve(self._symbolic, X)
        out = np.array(X, dtype=np.float64).reshape(B2.shape)
        return out.reshape(-1) if vec else out
