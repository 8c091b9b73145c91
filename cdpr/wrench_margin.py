"""The capacity margin: how far inside the wrenches the cables can give lies the wrench a
pose needs (the measure of the wrench-feasible workspace).

With tensions t in [t_lo, t_hi] the platform receives the wrenches W = {A t} (A = Lambda^T,
6 x n), a zonotope.  A pose is wrench-feasible when the wrench it needs, w, lies in W; its
margin is the radius of the largest ball of wrenches around w inside W: every disturbance
up to that size can still be balanced.  Forces and moments are made comparable by a length
l (`wrench_length`): a moment M counts as the force M / l (N).

The hyperplane shifting method (Bouchard, Moore and Gosselin 2010; Gouttefarde and Krut
2010): every facet of W is parallel to m - 1 of its generators a_j (m = 6), so its normal c
is orthogonal to them.  Rather than one normal per (m - 1)-subset S through determinants,
the normal is found in tension space: v = A^T c vanishes on S and is orthogonal to the
kernel K of A (n x k, k = n - m), so on the complement T of S (k + 1 cables) v_T is the
generalised cross product of K's rows T, and c = (A A^T)^-1 A v.  The facet pair +-c then
lies at sum_T |v_j| r_j +- v . (t_mid - t_p) from w along c (r the half ranges, t_mid the
middles, t_p any tensions with A t_p = w), divided by |c|; the margin is the smallest over
all C(n, k + 1) pairs (negative: w outside W, by at least that much).

Compiled with numba: 56 facets of an 8-cable robot in ~2 us a pose, against ~60 us for the
same maths batched in numpy (whose per-pose cost is in its gathers and small products).
The tests hold the verdict equal to an independent LP (scipy's HiGHS) and the margin to
the distance to the facet the LP finds.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike, NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import cholesky, cholesky_solve, gram
from cdpr.dynamics import PlatformInertia

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

_DEGENERATE = 1e-12  # |c| below this (relative): the cables T span no facet


class Margin(NamedTuple):
    """A pose's margin (N; negative outside W) and the facet that limits it: the cables
    `at_limit` (indices) whose tensions bound it, each at its upper limit when
    `upper[j]`, else at its lower one."""

    value: float
    at_limit: tuple[int, ...]
    upper: tuple[bool, ...]


@njit(cache=True)
def _kernel(A: Array, R: Array, K: Array, pivots: NDArray[np.int64]) -> bool:
    """K = a basis of A's kernel (n x k columns) by Gauss-Jordan elimination on R (m x n,
    overwritten), each row pivoting on its largest entry; False if A lacks full row rank."""
    m, n = A.shape
    R[:, :] = A
    pivot_of_row = pivots[:m]
    is_pivot = pivots[m:]
    is_pivot[:] = 0
    scale = 0.0
    for i in range(m):
        for j in range(n):
            scale = max(scale, abs(A[i, j]))
    for r in range(m):
        # partial pivoting along the row: its largest entry among the columns left
        best, bj = -1.0, -1
        for j in range(n):
            if not is_pivot[j] and abs(R[r, j]) > best:
                best, bj = abs(R[r, j]), j
        if best <= 1e-12 * scale:
            return False
        inv = 1.0 / R[r, bj]
        for j in range(n):
            R[r, j] *= inv
        for i in range(m):
            if i != r and R[i, bj] != 0.0:
                f = R[i, bj]
                for j in range(n):
                    R[i, j] -= f * R[r, j]
        pivot_of_row[r] = bj
        is_pivot[bj] = 1
    K[:, :] = 0.0
    col = 0
    for f in range(n):
        if is_pivot[f]:
            continue
        K[f, col] = 1.0
        for r in range(m):
            K[pivot_of_row[r], col] = -R[r, f]
        col += 1
    return True


@njit(cache=True)
def _cross(KT: Array, v: Array) -> None:
    """v = the generalised cross product of KT's k columns (KT: (k + 1) x k): the vector
    orthogonal to all of them, by cofactors (k = 0: 1)."""
    rows, k = KT.shape
    if k == 0:
        v[0] = 1.0
    elif k == 1:
        v[0], v[1] = KT[1, 0], -KT[0, 0]
    elif k == 2:
        v[0] = KT[1, 0] * KT[2, 1] - KT[2, 0] * KT[1, 1]
        v[1] = KT[2, 0] * KT[0, 1] - KT[0, 0] * KT[2, 1]
        v[2] = KT[0, 0] * KT[1, 1] - KT[1, 0] * KT[0, 1]
    else:
        minor = np.empty((k, k))
        for skip in range(rows):
            r = 0
            for i in range(rows):
                if i != skip:
                    minor[r, :] = KT[i, :]
                    r += 1
            sign = 1.0 if skip % 2 == 0 else -1.0
            v[skip] = sign * _det(minor)


@njit(cache=True)
def _facet_vector(K: Array, cables: NDArray[np.int64], KT: Array, v: Array) -> None:
    """v = v_T of the facet off `cables` (T): the generalised cross product of the
    kernel basis K's rows T (KT: scratch, (k + 1) x k)."""
    for i in range(KT.shape[0]):
        for j in range(KT.shape[1]):
            KT[i, j] = K[cables[i], j]
    _cross(KT, v)


@njit(cache=True)
def _det(M: Array) -> float:
    """The determinant of a small matrix by elimination with partial pivoting
    (overwrites M)."""
    k = M.shape[0]
    det = 1.0
    for c in range(k):
        p = c
        for i in range(c + 1, k):
            if abs(M[i, c]) > abs(M[p, c]):
                p = i
        if M[p, c] == 0.0:
            return 0.0
        if p != c:
            for j in range(k):
                M[c, j], M[p, j] = M[p, j], M[c, j]
            det = -det
        det *= M[c, c]
        for i in range(c + 1, k):
            f = M[i, c] / M[c, c]
            for j in range(c, k):
                M[i, j] -= f * M[c, j]
    return det


@njit(cache=True)
def margin_scratch(
    m: int, n: int
) -> tuple[Array, Array, Array, Array, Array, Array, Array, Array, NDArray[np.int64]]:
    """Work arrays of margin_kernel, allocated once per batch (or thread): R, K, G, L,
    X, H, K's rows T, the vectors (y, delta, half, v), pivots."""
    k = n - m
    return (
        np.empty((m, n)),
        np.empty((n, k)),
        np.empty((m, m)),
        np.zeros((m, m)),
        np.empty((m, n)),
        np.empty((n, n)),
        np.empty((k + 1, k)),
        np.empty((4, max(m, n))),
        np.empty(m + n, np.int64),
    )


@njit(cache=True)
def _solve_columns(L: Array, X: Array) -> None:
    """X = (L L^T)^-1 X in place, column by column."""
    m, n = X.shape
    for j in range(n):
        for i in range(m):
            s = X[i, j]
            for q in range(i):
                s -= L[i, q] * X[q, j]
            X[i, j] = s * L[i, i]
        for i in range(m - 1, -1, -1):
            s = X[i, j]
            for q in range(i + 1, m):
                s -= L[q, i] * X[q, j]
            X[i, j] = s * L[i, i]


@njit(cache=True)
def _facet_distance(reach: float, offset: float, size: float, norm2: float) -> float:
    """A facet's signed distance (reach - |offset|) / |c| from its sums over the facet's
    cables (|c|^2 = norm2); inf where c vanishes (the cables span no facet: skipped)."""
    norm = math.sqrt(max(norm2, 0.0))
    if norm <= _DEGENERATE * size:
        return math.inf
    return (reach - abs(offset)) / norm


@njit(cache=True)
def margin_kernel(
    A: Array,
    w: Array,
    lo: Array,
    hi: Array,
    combos: NDArray[np.int64],
    v_best: Array,
    work: tuple[Array, Array, Array, Array, Array, Array, Array, Array, NDArray[np.int64]],
) -> tuple[float, int, float]:
    """(margin, limiting facet, side) of wrench w in {A t : lo <= t <= hi} (A = the
    scaled Lambda^T); v_best gets the limiting facet's v_T.  -inf (facet -1) where A
    lacks full row rank.  For compiled callers: WrenchMargin wraps it."""
    m, n = A.shape
    R, K, G, L, X, H, KT, vectors, pivots = work
    full = _kernel(A, R, K, pivots)
    gram(A, G)
    if not (full and cholesky(G, L)):
        return -np.inf, -1, 0.0
    # t_p = A^T G^-1 w (the least-norm tensions giving w), then delta = t_p - t_mid
    y = vectors[0, :m]
    y[:] = w
    cholesky_solve(L, y)
    # X = G^-1 A, so that c = X v and |c|^2 = v^T H v with H = X^T X (n x n)
    X[:, :] = A
    _solve_columns(L, X)
    gram(X.T, H)
    delta = vectors[1, :n]
    half = vectors[2, :n]
    for j in range(n):
        s = -0.5 * (lo[j] + hi[j])
        for i in range(m):
            s += A[i, j] * y[i]
        delta[j] = s
        half[j] = 0.5 * (hi[j] - lo[j])
    k = n - m
    if k == 2:
        return _facets_of_a_plane_kernel(K, H, delta, half, combos, v_best)
    v = vectors[3, : k + 1]
    best, facet, side = np.inf, -1, 0.0
    for f in range(combos.shape[0]):
        _facet_vector(K, combos[f], KT, v)
        reach = 0.0
        offset = 0.0
        size = 0.0
        norm2 = 0.0
        for j in range(k + 1):
            t = combos[f, j]
            vj = v[j]
            reach += abs(vj) * half[t]
            offset += vj * delta[t]
            size += abs(vj)
            for i in range(k + 1):
                norm2 += vj * H[t, combos[f, i]] * v[i]
        distance = _facet_distance(reach, offset, size, norm2)
        if distance < best:
            best, facet = distance, f
            side = 1.0 if offset >= 0.0 else -1.0
            v_best[:] = v
    return best, facet, side


@njit(cache=True)
def _facets_of_a_plane_kernel(
    K: Array, H: Array, delta: Array, half: Array, combos: NDArray[np.int64], v_best: Array
) -> tuple[float, int, float]:
    """margin_kernel's loop over the facets where the kernel is a plane (k = 2: eight
    cables in six dimensions, the reference robot's case), unrolled: each facet's v_T is
    three 2-D cross products of K's rows and |c|^2 reads six entries of H.  The same
    numbers as the general loop (bar rounding), in a third of its time."""
    best, facet, side = np.inf, -1, 0.0
    for f in range(combos.shape[0]):
        a, b, c = combos[f, 0], combos[f, 1], combos[f, 2]
        v0 = K[b, 0] * K[c, 1] - K[c, 0] * K[b, 1]
        v1 = K[c, 0] * K[a, 1] - K[a, 0] * K[c, 1]
        v2 = K[a, 0] * K[b, 1] - K[b, 0] * K[a, 1]
        reach = abs(v0) * half[a] + abs(v1) * half[b] + abs(v2) * half[c]
        offset = v0 * delta[a] + v1 * delta[b] + v2 * delta[c]
        size = abs(v0) + abs(v1) + abs(v2)
        norm2 = v0 * v0 * H[a, a] + v1 * v1 * H[b, b] + v2 * v2 * H[c, c]
        norm2 += 2.0 * (v0 * v1 * H[a, b] + v0 * v2 * H[a, c] + v1 * v2 * H[b, c])
        distance = _facet_distance(reach, offset, size, norm2)
        if distance < best:
            best, facet = distance, f
            side = 1.0 if offset >= 0.0 else -1.0
            v_best[0], v_best[1], v_best[2] = v0, v1, v2
    return best, facet, side


@njit(cache=True)
def _margins_between(
    As: Array,
    ws: Array,
    lo: Array,
    hi: Array,
    combos: NDArray[np.int64],
    out: Array,
    begin: int,
    end: int,
) -> None:
    """out[p] = the margin of pose p, for p in [begin, end), on this thread."""
    work = margin_scratch(As.shape[1], As.shape[2])
    v = np.empty(combos.shape[1])
    for p in range(begin, end):
        out[p] = margin_kernel(As[p], ws[p], lo, hi, combos, v, work)[0]


@njit(cache=True)
def margin_bound_kernel(
    A: Array,
    w: Array,
    lo: Array,
    hi: Array,
    work: tuple[Array, Array, Array, Array, Array, Array, Array, Array, NDArray[np.int64]],
) -> float:
    """A lower bound of margin_kernel's margin, without its facets (on a long path's
    poses near home it spares ~2.5 us a pose: validate_long 0.78-0.85 -> 0.53 s):
    the least-norm tensions about the middle of [lo, hi], t* = t_mid + A^T G^-1 (w -
    A t_mid) (G = A A^T), give w, and t* + A^T G^-1 e gives w + e, inside [lo, hi] while
    |e| <= r = min_j slack_j / |column j of G^-1 A| (slack_j = t*_j's distance to its
    nearer bound): the ball of radius r about w lies in W.  -inf where t* leaves the box
    (no bound) or G is singular."""
    m, n = A.shape
    G, L, X, vectors = work[2], work[3], work[4], work[7]
    gram(A, G)
    if not cholesky(G, L):
        return -np.inf
    y = vectors[0, :m]
    for i in range(m):
        s = w[i]
        for j in range(n):
            s -= A[i, j] * 0.5 * (lo[j] + hi[j])
        y[i] = s
    cholesky_solve(L, y)
    X[:, :] = A
    _solve_columns(L, X)
    bound = np.inf
    for j in range(n):
        t = 0.5 * (lo[j] + hi[j])
        norm2 = 0.0
        for i in range(m):
            t += A[i, j] * y[i]
            norm2 += X[i, j] * X[i, j]
        slack = min(t - lo[j], hi[j] - t)
        if slack < 0.0:
            return -np.inf
        if norm2 > 0.0:
            bound = min(bound, slack / math.sqrt(norm2))
    return bound


@njit(cache=True)
def _short_of(
    As: Array,
    ws: Array,
    lo: Array,
    hi: Array,
    combos: NDArray[np.int64],
    required: float,
    out: NDArray[np.bool_],
) -> None:
    """out[p]: pose p's margin is below `required`, the exact margin computed only where
    the bound does not reach it."""
    work = margin_scratch(As.shape[1], As.shape[2])
    v = np.empty(combos.shape[1])
    for p in range(As.shape[0]):
        if margin_bound_kernel(As[p], ws[p], lo, hi, work) >= required:
            out[p] = False
        else:
            out[p] = margin_kernel(As[p], ws[p], lo, hi, combos, v, work)[0] < required


@njit(cache=True, parallel=True)
def _margins(
    As: Array, ws: Array, lo: Array, hi: Array, combos: NDArray[np.int64], out: Array
) -> None:
    """_margins_between over every pose, in chunks on every core."""
    count = As.shape[0]
    chunks = min(count, 64)
    for c in prange(chunks):
        _margins_between(
            As, ws, lo, hi, combos, out, c * count // chunks, (c + 1) * count // chunks
        )


@njit(cache=True)
def _normals_between(
    As: Array, combos: NDArray[np.int64], out: Array, begin: int, end: int
) -> None:
    """out[p, f] = the unit normal c of facet f of pose p's zonotope, for p in [begin,
    end) (zero where its cables T span no facet, or A lacks full row rank)."""
    m, n = As.shape[1], As.shape[2]
    R, K, G, L, X, _, KT, vectors, pivots = margin_scratch(m, n)
    k = n - m
    v = vectors[3, : k + 1]
    for p in range(begin, end):
        A = As[p]
        out[p] = 0.0
        if not _kernel(A, R, K, pivots):
            continue
        gram(A, G)
        if not cholesky(G, L):
            continue
        X[:, :] = A
        _solve_columns(L, X)  # G^-1 A: c = X v
        for f in range(combos.shape[0]):
            _facet_vector(K, combos[f], KT, v)
            norm2 = 0.0
            size = 0.0
            for i in range(m):
                c = 0.0
                for j in range(k + 1):
                    c += X[i, combos[f, j]] * v[j]
                out[p, f, i] = c
                norm2 += c * c
            for j in range(k + 1):
                size += abs(v[j])
            norm = math.sqrt(norm2)
            if norm <= _DEGENERATE * size:
                out[p, f] = 0.0
            else:
                for i in range(m):
                    out[p, f, i] /= norm


@njit(cache=True, parallel=True)
def _normals(As: Array, combos: NDArray[np.int64], out: Array) -> None:
    """_normals_between over every pose, in chunks on every core."""
    count = As.shape[0]
    chunks = min(count, 64)
    for c in prange(chunks):
        _normals_between(As, combos, out, c * count // chunks, (c + 1) * count // chunks)


def facet_cables(n: int, dof: int) -> NDArray[np.int64]:
    """The cables T off each facet pair of n cables in `dof` degrees of freedom: every
    (n - dof + 1)-subset, in itertools' order (the facets' order everywhere here)."""
    return np.array(list(itertools.combinations(range(n), n - dof + 1)), np.int64)


def facet_normals(jacobians: ArrayLike, parallel: bool = True) -> Array:
    """The unit normals c of every facet of the zonotope {Lambda^T t} at each pose
    (Jacobians N x n x dof, wrenches unscaled), one per facet pair +-c: N x C(n, k + 1)
    x dof, zero where the subset spans no facet.  The same hyperplane shifting as the
    margins (module docstring), for callers that put their own offsets on the facets
    (cdpr.path.timing)."""
    J = np.asarray(jacobians, dtype=float)
    count, n, dof = J.shape
    combos = facet_cables(n, dof)
    A = np.ascontiguousarray(np.swapaxes(J, 1, 2))
    out = np.empty((count, len(combos), dof))
    if parallel:
        _normals(A, combos, out)
    else:
        _normals_between(A, combos, out, 0, count)
    return out


def wrench_length(attachments: ArrayLike) -> float:
    """The length (m) that turns moments into forces: the attachments' RMS distance from
    the reference point (reference8: 0.41 m, so 10 N m counts as 24 N)."""
    b = np.asarray(attachments, dtype=float)
    return float(np.sqrt(np.mean(np.sum(b * b, axis=1))))


class WrenchMargin:
    """Capacity margins of one robot: tension limits `t_lo`, `t_hi` (N, per cable) and
    the moment length `length` (m)."""

    def __init__(self, t_lo: ArrayLike, t_hi: ArrayLike, length: float, dof: int = 6) -> None:
        self.t_lo = np.ascontiguousarray(t_lo, dtype=float)
        self.t_hi = np.ascontiguousarray(t_hi, dtype=float)
        n = self.t_lo.size
        if self.t_hi.size != n or not np.all(self.t_hi > self.t_lo):
            raise ValueError(f"tension limits need t_lo < t_hi per cable: {self.t_lo}, {self.t_hi}")
        if n < dof:
            raise ValueError(f"{n} cables cannot give every wrench of {dof} degrees of freedom")
        self.length = float(length)
        self.dof = dof
        self.combos = facet_cables(n, dof)
        # Lambda's columns are [force | moment]; a moment counts as moment / length
        self.scale = np.ones(dof)
        self.scale[dof // 2 :] = 1.0 / self.length
        self._v = np.empty(n - dof + 1)
        self._work = margin_scratch(dof, n)

    def margin(self, jacobian: ArrayLike, wrench: ArrayLike) -> Margin:
        """The margin of `wrench` (N, N m) at a pose with Jacobian Lambda (n x dof)."""
        A = np.ascontiguousarray(np.asarray(jacobian, dtype=float).T * self.scale[:, None])
        w = np.asarray(wrench, dtype=float) * self.scale
        value, facet, side = margin_kernel(
            A, w, self.t_lo, self.t_hi, self.combos, self._v, self._work
        )
        if facet < 0:
            return Margin(float(value), (), ())
        cables = tuple(int(j) for j in self.combos[facet])
        upper = tuple(bool(side * x > 0.0) for x in self._v)
        return Margin(float(value), cables, upper)

    def margins(self, jacobians: ArrayLike, wrenches: ArrayLike, parallel: bool = True) -> Array:
        """Margins (N) of many poses: Jacobians (N x n x dof), wrenches (N x dof); on
        every core, or on this thread only (`parallel` False: inside the daemon)."""
        A, w = self._scaled(jacobians, wrenches)
        out = np.empty(len(A))
        if parallel:
            _margins(A, w, self.t_lo, self.t_hi, self.combos, out)
        else:
            _margins_between(A, w, self.t_lo, self.t_hi, self.combos, out, 0, len(A))
        return out

    def short_of(
        self, jacobians: ArrayLike, wrenches: ArrayLike, required: float
    ) -> NDArray[np.bool_]:
        """Which poses' margins fall below `required` (N), on this thread: the exact
        margin only where margin_bound_kernel's bound does not reach it (near W's edge;
        most poses of a path are not)."""
        A, w = self._scaled(jacobians, wrenches)
        out = np.empty(len(A), np.bool_)
        _short_of(A, w, self.t_lo, self.t_hi, self.combos, float(required), out)
        return out

    def _scaled(self, jacobians: ArrayLike, wrenches: ArrayLike) -> tuple[Array, Array]:
        """(A, w) of each pose in the units the margin is in: moments / length."""
        J = np.asarray(jacobians, dtype=float)
        A = np.ascontiguousarray(np.swapaxes(J, 1, 2) * self.scale[:, None])
        return A, np.ascontiguousarray(np.asarray(wrenches, dtype=float) * self.scale)


def rest_wrenches(
    platform: PlatformInertia,
    rotations: ArrayLike,
    payload: float = 0.0,
    payload_com: ArrayLike = (0.0, 0.0, 0.0),
) -> Array:
    """The wrench the cables must give (Lambda^T t) to hold the platform at rest at each
    rotation (N x 3 x 3), with a `payload` (kg) at `payload_com` (platform frame, m):
    [m g ; (R m c) x g], N x 6 (the robot's -mu at zero twist)."""
    cb = np.asarray(platform.center_of_mass, dtype=float)
    mass = platform.mass + payload
    first_moment = platform.mass * cb + payload * np.asarray(payload_com, dtype=float)
    g = np.asarray(platform.gravity, dtype=float)
    R = np.asarray(rotations, dtype=float)
    moments = np.cross(R.dot(first_moment), g)
    forces = np.broadcast_to(mass * g, moments.shape)
    return np.concatenate([forces, moments], axis=1)
