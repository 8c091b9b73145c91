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
from numpy.typing import NDArray

Array = NDArray[np.float64]

_NEWTON = 6  # refinements of each knot's time (timed_at)
_TABLE = 16  # table points per window width for the first guess of a knot's time


class TimeLaw:
    """s(t) through `grid` (N path points, from 0) at `speeds` (N, s' >= 0, 0 at both ends)
    with the constant `accels` (N - 1) between them, reached at `times` (N, from 0)."""

    def __init__(self, grid: Array, speeds: Array, accels: Array, times: Array) -> None:
        self.t, self.s, self.v, self.u = times, grid, speeds, accels
        h = np.diff(times)
        # the integral of s from 0 to each grid time
        pieces = grid[:-1] * h + speeds[:-1] * h**2 / 2 + accels * h**3 / 6
        self.S = np.concatenate([[0.0], np.cumsum(pieces)])
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
        the end's): a table's interpolation refined by guarded Newton steps."""
        table_t = np.linspace(0.0, self.end, max(2, int(_TABLE * self.end / self.width)) + 1)
        table_s = self.at(table_t)[0]
        t = np.interp(s, table_s, table_t)
        j = np.clip(np.searchsorted(table_s, s, side="right"), 1, len(table_t) - 1)
        lo, hi = table_t[j - 1], table_t[j]
        for _ in range(_NEWTON):
            value, rate, _ = self.at(t)
            step = np.where(rate > 0.0, (value - s) / np.where(rate > 0.0, rate, 1.0), 0.0)
            t = np.clip(t - step, lo, hi)
        t[0], t[-1] = 0.0, self.end
        return t
