"""Small dense linear algebra for the compiled kernels (numba), where a LAPACK call from
Python would cost more than the 6 x 6 work itself: a Cholesky factor (with the inverse
of its diagonal, which the solves multiply by), its solve, a Gram matrix.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from cdpr.compiled_cache import key_numba_cache

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]
F64 = np.dtype(np.float64)  # float64 arrays share one dtype object


def kernel_array(x: ArrayLike, shape: tuple[int, ...]) -> Array | None:
    """x as the kernels take it (float64, contiguous, writable: one type to numba, a copy
    if need be), or None if it is not numbers of that shape (the caller then says why)."""
    if type(x) is not np.ndarray or x.dtype is not F64:
        try:
            x = np.array(x, dtype=float)
        except (TypeError, ValueError):
            return None
    if x.shape != shape:
        return None
    flags = x.flags
    return x if flags.c_contiguous and flags.writeable else np.array(x)


@njit(cache=True)
def cholesky(G: Array, L: Array) -> bool:
    """G = L L^T into L, with 1 / L_ii on its diagonal (the solves multiply by it);
    False unless G is positive definite."""
    m = G.shape[0]
    for i in range(m):
        for j in range(i + 1):
            s = G[i, j]
            for q in range(j):
                s -= L[i, q] * L[j, q]
            if i == j:
                if s <= 0.0:
                    return False
                L[i, i] = 1.0 / math.sqrt(s)
            else:
                L[i, j] = s * L[j, j]
    return True


@njit(cache=True)
def cholesky_solve(L: Array, z: Array) -> None:
    """z = (L L^T)^-1 z in place (L from cholesky): forward, then back substitution."""
    m = L.shape[0]
    for i in range(m):
        s = z[i]
        for q in range(i):
            s -= L[i, q] * z[q]
        z[i] = s * L[i, i]
    for i in range(m - 1, -1, -1):
        s = z[i]
        for q in range(i + 1, m):
            s -= L[q, i] * z[q]
        z[i] = s * L[i, i]


@njit(cache=True)
def gram(M: Array, out: Array) -> None:
    """out = M M^T (symmetric: each pair of rows once)."""
    rows, cols = M.shape
    for a in range(rows):
        for b in range(a + 1):
            s = 0.0
            for q in range(cols):
                s += M[a, q] * M[b, q]
            out[a, b] = s
            out[b, a] = s


@njit(cache=True)
def upper_solve(U: Array, z: Array) -> None:
    """z = (U^T U)^-1 z in place for an upper Cholesky factor U as LAPACK's dpotrf
    leaves it (cdpr.forward_kinematics.FKResult.normal_factor): dpotrs in a kernel."""
    m = U.shape[0]
    for i in range(m):
        s = z[i]
        for q in range(i):
            s -= U[q, i] * z[q]
        z[i] = s / U[i, i]
    for i in range(m - 1, -1, -1):
        s = z[i]
        for q in range(i + 1, m):
            s -= U[i, q] * z[q]
        z[i] = s / U[i, i]


@njit(cache=True)
def left_null_space(A: Array, N: Array) -> None:
    """N (m x (m - n)): an orthonormal basis of the left null space of A (m x n, m > n),
    the last m - n columns of Q in A = Q R by Householder reflections: N^T A = 0 and
    N^T N = I whatever A's rank (a LAPACK SVD from Python took 0.1 ms in the cycle)."""
    m, n = A.shape
    R = A.copy()
    V = np.zeros((n, m))  # the reflections' unit vectors, row k acting on rows k..m-1
    for k in range(n):
        norm = 0.0
        for i in range(k, m):
            norm += R[i, k] * R[i, k]
        norm = math.sqrt(norm)
        if norm == 0.0:
            continue  # nothing below the diagonal to reflect away: H_k = I
        alpha = -norm if R[k, k] >= 0.0 else norm
        length = 0.0
        for i in range(k, m):
            V[k, i] = R[i, k]
        V[k, k] -= alpha
        for i in range(k, m):
            length += V[k, i] * V[k, i]
        length = math.sqrt(length)
        for i in range(k, m):
            V[k, i] /= length
        for j in range(k, n):  # R = H_k R on the columns still to reduce
            s = 0.0
            for i in range(k, m):
                s += V[k, i] * R[i, j]
            for i in range(k, m):
                R[i, j] -= 2.0 * s * V[k, i]
    for c in range(m - n):  # Q e_(n + c) = H_0 H_1 ... H_(n-1) e_(n + c)
        for i in range(m):
            N[i, c] = 0.0
        N[n + c, c] = 1.0
        for k in range(n - 1, -1, -1):
            s = 0.0
            for i in range(k, m):
                s += V[k, i] * N[i, c]
            for i in range(k, m):
                N[i, c] -= 2.0 * s * V[k, i]
