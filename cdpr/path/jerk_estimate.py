"""The largest jerk of the quintic Hermite segments through a motion's knots, without
building them (compiled).

The path timing's jerk filter (cdpr.path.timing) compares averaging windows by the jerk
each leaves: building each window's trajectory and measuring it took 12 ms on a
100-pose path, and evaluating the quintics' third derivatives with numpy ~2 ms; this
loop takes them segment by segment at the instants validation measures the jerk at
(cdpr.trajectory.jerk).  Between knots k and k + 1, h apart, with the step D, the rates
V and the accelerations A at both ends, each coordinate's quintic has the third
derivative 6 c3 + 24 c4 tau + 60 c5 tau^2 (c3, c4, c5 below); positions exactly, the
rotation vector's quintic as an estimate (exact about one fixed axis).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]


@njit(cache=True)
def jerk_peaks(
    times: Array, steps: Array, twists: Array, accels: Array, instants: Array
) -> tuple[float, float]:
    """(largest linear, largest angular) jerk norm of the quintics through knots at
    `times` (n) with `steps` between them (n - 1, 6: position and rotation-vector steps),
    `twists` and `accels` (n, 6), at `instants` (fractions of each segment)."""
    linear, angular = 0.0, 0.0
    c3, c4, c5 = np.empty(6), np.empty(6), np.empty(6)
    for i in range(len(times) - 1):
        h = times[i + 1] - times[i]
        h2 = h * h
        for j in range(6):
            D, V0, V1 = steps[i, j], twists[i, j], twists[i + 1, j]
            A0, A1 = accels[i, j], accels[i + 1, j]
            c3[j] = (20.0 * D - (8.0 * V1 + 12.0 * V0) * h - (3.0 * A0 - A1) * h2) / (2.0 * h2 * h)
            c4[j] = (-30.0 * D + (14.0 * V1 + 16.0 * V0) * h + (3.0 * A0 - 2.0 * A1) * h2) / (
                2.0 * h2 * h2
            )
            c5[j] = (12.0 * D - 6.0 * (V1 + V0) * h - (A0 - A1) * h2) / (2.0 * h2 * h2 * h)
        for fraction in instants:
            tau = fraction * h
            lin, ang = 0.0, 0.0
            for j in range(6):
                jerk = 6.0 * c3[j] + (24.0 * c4[j] + 60.0 * c5[j] * tau) * tau
                if j < 3:
                    lin += jerk * jerk
                else:
                    ang += jerk * jerk
            linear = max(linear, math.sqrt(lin))
            angular = max(angular, math.sqrt(ang))
    return linear, angular
