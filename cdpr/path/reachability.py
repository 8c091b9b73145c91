"""TOPP-RA's two passes (Pham and Pham 2018, sec. IV), compiled.

At each grid point i of a path the path acceleration u = s'' and the squared speed
x = s'^2 must satisfy the point's rows a[i] u + b[i] x + c[i] <= 0 and X[i, 0] <= x <=
X[i, 1]; from one grid point to the next x_{i+1} = x_i + 2 d_i u_i.  Stage i (the
interval from point i) holds its (u, x) to the rows of point i, and to those of point
i + 1 for the same u at x + 2 d_i u (TOPP-RA's interpolation scheme): both ends of the
interval then hold its acceleration, and a knot holds the mean of its two intervals'.

- Backward (`controllable_sets`): K[N] = [0, 0] (at rest at the end); K[i] is the range
  of x from which some feasible u lands in K[i + 1]: two linear programs in (u, x) per
  stage, its lowest and highest x (Seidel's incremental algorithm, which solves a
  two-variable program in time linear in its rows; the rows that bounded the last
  stage's optimum are tried first, and usually bound this one's).
- Forward (`parameterize`): from x_0 = 0 the largest u at each stage whose next x stays
  in K[i + 1] (a program in u alone); where rounding leaves no u, x_i is lowered by
  TINY, then twice as much, until one is found.

The `toppra` package (the authors' implementation) steps these passes in Python, about
50 us per grid point and pass on this 2-vCPU host plus 20 us of set-up: timing a
100-pose path took 0.3 s.  Compiled they take about a microsecond a grid point.
tests/cdpr/test_reachability.py holds them to toppra on the daemon's own paths.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

TINY = 1e-10  # a coefficient smaller than this bounds nothing
SMALL = 1e-8  # what a row parallel to the optimum's line may be violated by
BOUND = 1e8  # |u| never exceeds it: the programs' box
TRIES = 60  # a forward step without a feasible u retries from x_i lowered by TINY, 2 TINY, ...


class Parameterization(NamedTuple):
    """The timed path: `u` (N path accelerations, one per interval), `speed` (N + 1 path
    speeds), the controllable sets `K` ((N + 1) x 2 squared speeds), and `failed`: the
    stage where no speed was controllable or the forward pass found no acceleration
    (u and speed then NaN from that stage on), -1 when none."""

    u: Array
    speed: Array
    K: Array
    failed: int


def parameterize(A: Array, B: Array, C: Array, X: Array, grid: Array) -> Parameterization:
    """The time-optimal parameterization from rest to rest on `grid` (N + 1 points) of
    the points' rows A, B, C ((N + 1) x m) and x bounds X ((N + 1) x 2), stage by stage
    as the module docstring says."""
    A, B, C, X = (np.ascontiguousarray(v, dtype=float) for v in (A, B, C, X))
    deltas = np.diff(np.asarray(grid, dtype=float))
    K = np.zeros((len(deltas) + 1, 2))
    failed = _controllable(A, B, C, X, deltas, K)
    n = len(deltas)
    u, x = np.full(n, np.nan), np.full(n + 1, np.nan)
    if failed < 0:
        failed = _forward(A, B, C, X, deltas, K, u, x)
    speed = np.sqrt(np.maximum(x, 0.0))
    return Parameterization(u, speed, K, failed)


@njit(cache=True)
def load_factor(A: Array, B: Array, C: Array, u: Array, x: Array) -> float:
    """The largest (A[i] u_i + B[i] x_i) / -C[i] over the rows with C < 0 of every grid
    point i (0 if none): a timing (u, x) scaled by 1 / that factor (u and x both, a
    slower time law) holds those rows with equality at worst."""
    worst = 0.0
    for i in range(A.shape[0]):
        ui, xi = u[i], x[i]
        for r in range(A.shape[1]):
            c = C[i, r]
            if c < 0.0:
                worst = max(worst, (A[i, r] * ui + B[i, r] * xi) / -c)
    return worst


@njit(cache=True)
def _stage(A, B, C, i, delta, k_lo, k_hi, a, b, c):
    """Stage i's rows into a, b, c: point i's, point i + 1's at x + 2 d u, then x + 2 d u
    <= k_hi and x + 2 d u >= k_lo (module docstring)."""
    m = A.shape[1]
    for j in range(m):
        a[j], b[j], c[j] = A[i, j], B[i, j], C[i, j]
        following = B[i + 1, j]
        a[m + j] = A[i + 1, j] + 2.0 * delta * following
        b[m + j], c[m + j] = following, C[i + 1, j]
    a[2 * m], b[2 * m], c[2 * m] = 2.0 * delta, 1.0, -k_hi
    a[2 * m + 1], b[2 * m + 1], c[2 * m + 1] = -2.0 * delta, -1.0, k_lo


@njit(cache=True)
def _clip(p, d, lo, hi, t_lo, t_hi):
    """(t_lo, t_hi) narrowed to the t where lo <= p + t d <= hi (a box side)."""
    if d > TINY:
        t_lo, t_hi = max(t_lo, (lo - p) / d), min(t_hi, (hi - p) / d)
    elif d < -TINY:
        t_lo, t_hi = max(t_lo, (hi - p) / d), min(t_hi, (lo - p) / d)
    return t_lo, t_hi


@njit(cache=True)
def _extreme(a, b, c, x_lo, x_hi, sign, order):
    """The highest (sign 1) or lowest (sign -1) x of a stage's program (its rows a u + b x
    + c <= 0, x in [x_lo, x_hi], |u| <= BOUND), NaN if it has none.  Seidel's
    algorithm: rows added in `order`; where the optimum so far violates one, the new
    optimum lies on its line, bounded by the rows before it and the box.  Each row that
    moved the optimum moves to the front of `order` (the rows before it stay before the
    ones after): the next stage, much like this one, meets it early, where a row that
    moves the optimum costs a pass over fewer rows before it."""
    vu, vx = -sign * 1e-9, float(sign)  # the tie-break on u as toppra sets it
    if x_lo > x_hi:
        return np.nan
    cu = BOUND if vu > TINY else -BOUND
    cx = x_hi if vx > TINY else x_lo
    for k in range(order.shape[0]):
        j = order[k]
        aj, bj, cj = a[j], b[j], c[j]
        if aj * cu + bj * cx + cj < TINY:
            continue
        n2 = aj * aj + bj * bj
        if n2 == 0.0:
            return np.nan  # 0 <= -c with c > 0
        pu, px = -aj * cj / n2, -bj * cj / n2  # the line's point nearest the origin
        du, dx = -bj, aj  # its direction
        t_lo, t_hi = _clip(pu, du, -BOUND, BOUND, -np.inf, np.inf)
        t_lo, t_hi = _clip(px, dx, x_lo, x_hi, t_lo, t_hi)
        for q in range(k):
            r = order[q]
            aq, bq, cq = a[r], b[r], c[r]
            den = aq * du + bq * dx
            val = aq * pu + bq * px + cq
            if den > TINY:
                t_hi = min(t_hi, -val / den)
            elif den < -TINY:
                t_lo = max(t_lo, -val / den)
            elif val > SMALL:
                return np.nan  # parallel to the line and cut off from it
        if t_lo > t_hi:
            return np.nan
        t = t_hi if vu * du + vx * dx > TINY else t_lo
        cu, cx = pu + t * du, px + t * dx
        for q in range(k, 0, -1):  # a row that moved the optimum goes first next stage
            order[q] = order[q - 1]
        order[0] = j
    return cx


@njit(cache=True)
def _controllable(A, B, C, X, deltas, K):
    """K filled from the end (module docstring); the stage that has no controllable x
    (its K NaN), or -1."""
    n = deltas.shape[0]
    rows = 2 * A.shape[1] + 2
    upper, lower = np.arange(rows), np.arange(rows)
    a, b, c = np.empty(rows), np.empty(rows), np.empty(rows)
    K[n, 0] = 0.0
    K[n, 1] = 0.0
    for i in range(n - 1, -1, -1):
        x_lo, x_hi = max(X[i, 0], 0.0), min(X[i, 1], BOUND)
        _stage(A, B, C, i, deltas[i], K[i + 1, 0], K[i + 1, 1], a, b, c)
        high = _extreme(a, b, c, x_lo, x_hi, 1.0, upper)
        low = _extreme(a, b, c, x_lo, x_hi, -1.0, lower)
        if np.isnan(high) or np.isnan(low):
            K[i, 0] = np.nan
            K[i, 1] = np.nan
            return i
        K[i, 0] = max(low, 0.0)
        K[i, 1] = high
    return -1


@njit(cache=True)
def _forward(A, B, C, X, deltas, K, u, x):
    """u and x filled from rest at the start (module docstring); the stage where no
    acceleration was found, or -1."""
    n = deltas.shape[0]
    rows = 2 * A.shape[1] + 2
    a, b, c = np.empty(rows), np.empty(rows), np.empty(rows)
    x[0] = 0.0
    if K[0, 0] > SMALL:
        return 0  # rest at the start is not controllable
    xi = 0.0
    for i in range(n):
        _stage(A, B, C, i, deltas[i], K[i + 1, 0], K[i + 1, 1], a, b, c)
        found, lower = False, TINY
        for _ in range(TRIES):
            lo, hi = -BOUND, BOUND
            feasible = X[i, 0] <= xi <= X[i, 1]
            for j in range(rows):
                aj, bound = a[j], -(b[j] * xi + c[j])
                if aj > TINY:
                    hi = min(hi, bound / aj)
                elif aj < -TINY:
                    lo = max(lo, bound / aj)
                elif bound < -SMALL:
                    feasible = False  # a row on x alone
            if feasible and lo <= hi:
                found = True
                break
            xi -= lower
            lower *= 2.0
            if xi < 0.0:
                break
        if not found:
            return i
        x[i] = xi
        u[i] = hi
        xi = max(xi + 2.0 * deltas[i] * hi, 0.0)
        x[i + 1] = xi
    return -1
