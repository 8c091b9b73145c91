"""A control cycle's measurement in one compiled kernel (cdpr.controller's step, the
paper's steps 3-5): the drums' lengths stretched by the planned tensions, forward
kinematics from the prepared linearisation, the platform's twist, and the pose error
against the reference.

Each piece is the maths of its own module, called from here: the stretch
L = l (1 + s t / EA) (Robot.stretched_lengths, cdpr.stretch), the Gauss-Newton fit and
its verdict (cdpr.forward_kinematics.fit_kernel), the pose difference
(cdpr.pose.pose_difference).
The twist is measured here (ParallelController._measure's docstring says why each way):
the least-squares phi = Lambda^+ (l' + stretch rate) on the fit's Lambda and normal
factor, with or without the complementary filter that takes its low frequencies from
the poses' differences, or the filtered differences alone.  One kernel because at
1 kHz the Python between the pieces cost more than the pieces did.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import upper_solve
from cdpr.forward_kinematics import CONVERGED, fit_kernel
from cdpr.pose import pose_difference

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

# how the twist is measured: from the drives' rates; from them with the complementary
# filter (elastic cables); from the poses' differences alone
FROM_RATES, FILTERED_RATES, DIFFERENTIATED = 0, 1, 2

# `memory`, what a cycle leaves the next: the pose (p, q), the twist, the drives' twist
# and the filter's rate bias
MEMORY_SIZE = 25
# `out`, the cycle's measurement: the pose (p, q), the twist, the pose error theta_d
# and its rate (actual minus requested)
OUT_SIZE = 25
POSE, TWIST, ERROR, ERROR_RATE = slice(0, 7), slice(7, 13), slice(13, 19), slice(19, 25)


@njit(cache=True)
def measure(
    cables: Array,
    drums: Array,
    compliance: Array,
    tensions: Array,
    scale: float,
    kind: int,
    start: Array,
    lengths0: Array,
    J0: Array,
    L0: Array,
    max_iterations: int,
    tolerance2: float,
    max_residual: float,
    rates: Array,
    stretch_rate: Array,
    mode: int,
    smoothing: float,
    interval: float,
    memory: Array,
    reference: Array,
    out: Array,
) -> tuple[int, bool, int, float, Array, Array, Array, Array, bool]:
    """The drums' `drums` stretched by `tensions` (at compliance scale `scale`), forward
    kinematics from `start` (p, q: the guess) as fit_kernel takes it (`kind`, `lengths0`,
    `J0`, `L0`, the settings), then, converged, the twist from `rates` (m/s, plus
    `stretch_rate` unless empty) by `mode`, over `interval` s since the pose in
    `memory`, and the pose error against `reference` (p, q, twist) into `out`.

    Returns fit_kernel's (status, ..., U, factored) with, second, whether the twist is finite:
    only then are `out` and `memory` (the pose, the twist) the new cycle's.  The
    filter's own memory moves whenever a twist from the rates is measured, as the
    Python it replaces did."""
    n = drums.shape[0]
    stretched = np.empty(n)
    for k in range(n):
        stretched[k] = drums[k] + drums[k] * compliance[k] * (tensions[k] * scale)
    status, iterations, residual, p, q, J, U, factored = fit_kernel(
        cables, stretched, (start[0], start[1], start[2]), (start[3], start[4], start[5], start[6]),
        kind, lengths0, J0, L0, max_iterations, tolerance2, max_residual,
    )  # fmt: skip
    if status != CONVERGED:
        return status, False, iterations, residual, p, q, J, U, factored
    twist = np.empty(6)
    if mode == DIFFERENTIATED:
        moved = pose_difference(memory[0:3], memory[3:7], p, q)
        for i in range(6):
            last = memory[7 + i]
            twist[i] = last + smoothing * (moved[i] / interval - last)
    elif not factored:  # singular normal equations
        twist[:] = math.nan
    else:
        for a in range(6):  # J^T l', then the normal equations
            s = 0.0
            for k in range(n):
                rate = rates[k] + stretch_rate[k] if stretch_rate.shape[0] else rates[k]
                s += rate * J[k, a]
            twist[a] = s
        upper_solve(U, twist)
        if mode == FILTERED_RATES:
            moved = pose_difference(memory[0:3], memory[3:7], p, q)
            for i in range(6):
                drive, bias = twist[i], memory[19 + i]
                bias += smoothing * (moved[i] / interval - 0.5 * (drive + memory[13 + i]) - bias)
                memory[13 + i], memory[19 + i] = drive, bias
                twist[i] = drive + bias
    total = 0.0
    for i in range(6):
        total += twist[i]
    if not math.isfinite(total):
        return status, False, iterations, residual, p, q, J, U, factored
    error = pose_difference(reference[0:3], reference[3:7], p, q)
    for i in range(3):
        out[i] = memory[i] = p[i]
    for i in range(4):
        out[3 + i] = memory[3 + i] = q[i]
    for i in range(6):
        out[7 + i] = memory[7 + i] = twist[i]
        out[13 + i] = error[i]
        out[19 + i] = twist[i] - reference[7 + i]
    return status, True, iterations, residual, p, q, J, U, factored
