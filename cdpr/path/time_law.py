"""A timed motion's time law s(t), and the same law averaged over a moving window.

TOPP-RA times a motion as a grid of path points s_i with speeds s'_i and a constant path
acceleration u_i on each interval: s(t) is piecewise quadratic, its acceleration steps
from one interval to the next (bang-bang), and a quintic through the grid points turns
each step into a jerk of (u_i+1 - u_i) / (the knots' spacing in time): hundreds of m/s³.

Averaged over a window of `width` s (an FIR filter, as CNC controllers smooth their
feed), s_w(t) = (1 / width) integral of s over [t - width, t]:

    s_w' = (s(t) - s(t - width)) / width,   s_w'' = (s'(t) - s'(t - width)) / width,
    s_w''' = (s''(t) - s''(t - width)) / width,

so the path's jerk is at most the range of s'' over a window divided by its width, the
speeds and accelerations are means of those of the law (never beyond its extremes), and
the motion ends `width` later, at rest with no acceleration as it began.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

_ITERATIONS = 100  # at most, per knot time (timed_at): Newton, bisecting where it leaves
_TOLERANCE = 1e-14  # of s_w's residual, relative to the path's length (timed_at)


class TimeLaw:
    """s(t) through `grid` (N path points, from 0) at `speeds` (N, s' >= 0, 0 at both ends)
    with the constant `accels` (N - 1) between them, reached at `times` (N, from 0)."""

    def __init__(self, grid: Array, speeds: Array, accels: Array, times: Array) -> None:
        self.t, self.s, self.v, self.u = times, grid, speeds, accels
        h = np.diff(times)
        # the integral of s from 0 to each grid time
        self.pieces = grid[:-1] * h + speeds[:-1] * h**2 / 2 + accels * h**3 / 6
        self.S = np.concatenate([[0.0], np.cumsum(self.pieces)])
        self.end = float(times[-1])

    def at(self, t: Array) -> tuple[Array, Array, Array]:
        """(integral of s from 0, s, s') at times `t`: rest before 0 and after the end."""
        t = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.u) - 1)
        d = np.clip(t, 0.0, self.end) - self.t[i]
        s0, v0, u = self.s[i], self.v[i], self.u[i]
        s = s0 + v0 * d + u * d * d / 2
        S = self.S[i] + s0 * d + v0 * d * d / 2 + u * d**3 / 6
        beyond = np.maximum(t - self.end, 0.0)
        v = np.where((t < 0.0) | (t > self.end), 0.0, v0 + u * d)
        return np.where(t < 0.0, 0.0, S + s * beyond), np.where(t < 0.0, 0.0, s), v


class AveragedLaw:
    """`law` averaged over `width` s (module docstring); `end` its duration."""

    def __init__(self, law: TimeLaw, width: float) -> None:
        self.law, self.width = law, width
        self.end = law.end + width

    def at(self, t: Array) -> tuple[Array, Array, Array]:
        """(s_w, s_w', s_w'') at times `t`."""
        S1, s1, v1 = self.law.at(t)
        S0, s0, v0 = self.law.at(np.asarray(t) - self.width)
        w = self.width
        return (S1 - S0) / w, (s1 - s0) / w, (v1 - v0) / w

    def timed_at(self, s: Array) -> Array:
        """The times at which s_w reaches each of the increasing path points `s` (from 0 to
        the end's): Newton's method from the law's own time plus half a window, kept
        inside a bracket that each point's time starts from the last one's and bisected
        where a step leaves it (compiled: _timed_at), to a residual of _TOLERANCE."""
        law = self.law
        s = np.ascontiguousarray(s, dtype=float)
        return _timed_at(s, law.t, law.s, law.v, law.u, law.pieces, law.end, self.width)


@njit(cache=True)
def _interval(t: float, times: Array) -> int:
    """The law's interval holding time t (clipped to the first and last)."""
    return min(max(np.searchsorted(times, t, side="right") - 1, 0), len(times) - 2)


@njit(cache=True)
def _part(i: int, d: float, s: Array, v: Array, u: Array) -> float:
    """The integral of s over the first d s of interval i."""
    return s[i] * d + v[i] * d * d / 2.0 + u[i] * d**3 / 6.0


@njit(cache=True)
def _window(
    t: float, width: float, times: Array, s: Array, v: Array, u: Array, pieces: Array
) -> float:
    """The integral of s over [t - width, t], summed over the intervals it spans (not a
    difference of integrals from 0, whose rounding grows with the path: on a 2,000-line
    part it stalled Newton's method)."""
    end = times[-1]
    a, b = max(t - width, 0.0), min(t, end)
    total = s[-1] * (t - max(t - width, end)) if t > end else 0.0
    if a >= b:
        return total
    i, k = _interval(a, times), _interval(b, times)
    if i == k:
        return total + _part(k, b - times[k], s, v, u) - _part(i, a - times[i], s, v, u)
    total += pieces[i] - _part(i, a - times[i], s, v, u) + _part(k, b - times[k], s, v, u)
    for m in range(i + 1, k):
        total += pieces[m]
    return total


@njit(cache=True)
def _speed(t: float, times: Array, s: Array, v: Array, u: Array) -> float:
    """s at time t (0 before the start, the end's after it)."""
    if t <= 0.0:
        return 0.0
    if t >= times[-1]:
        return s[-1]
    i = _interval(t, times)
    d = t - times[i]
    return s[i] + v[i] * d + u[i] * d * d / 2.0


@njit(cache=True)
def _timed_at(
    targets: Array,
    times: Array,
    s: Array,
    v: Array,
    u: Array,
    pieces: Array,
    end: float,
    width: float,
) -> Array:
    n = len(targets)
    out = np.empty(n)
    last = end + width
    tolerance = _TOLERANCE * max(1.0, s[-1])
    lo = 0.0
    j = 0  # the law's interval holding the target
    for k in range(n):
        target = targets[k]
        while j < len(s) - 2 and s[j + 1] <= target:
            j += 1
        span = s[j + 1] - s[j]
        share = (target - s[j]) / span if span > 0.0 else 0.0
        t = times[j] + share * (times[j + 1] - times[j]) + 0.5 * width
        hi = last
        if not lo < t < hi:
            t = 0.5 * (lo + hi)
        for _ in range(_ITERATIONS):
            residual = _window(t, width, times, s, v, u, pieces) / width - target
            if abs(residual) <= tolerance:
                break
            if residual > 0.0:
                hi = t
            else:
                lo = t
            rate = (_speed(t, times, s, v, u) - _speed(t - width, times, s, v, u)) / width
            step = t - residual / rate if rate > 0.0 else lo - 1.0
            t = step if lo < step < hi else 0.5 * (lo + hi)
            if hi - lo <= 1e-15 * last:
                break
        out[k] = t
        lo = t
    out[0], out[-1] = 0.0, last
    return out
