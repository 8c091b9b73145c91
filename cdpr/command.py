"""A control cycle's command in one compiled kernel (cdpr.controller's step, the paper's
steps 6-10, after cdpr.measurement): the single-actuator loop on the pose error, the
command wrench tau_c = M alpha_c + mu (less the external wrench observer's estimate),
the no-load forces f0 = m0 (Lambda alpha_c + c), and, where the least-norm tensions meet
every bound (most cycles), the tension distribution and the commands f_c = f0 - t + f_b.

Each piece is the maths of its own module, called from here: the loop's sample
(cdpr.single_actuator.advance), the least-norm tensions and their check
(cdpr.tension.least_norm_inside, as the solver's own shortcut runs them).  Where they
do not meet a bound the controller asks its solver (OSQP, Pott's method) in Python, with
the wrench and forces computed here.  One kernel because at 1 kHz the Python between the
pieces cost more than the pieces did.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.extending import register_jitable
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.measurement import ERROR, ERROR_RATE
from cdpr.single_actuator import advance
from cdpr.tension import least_norm_inside

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

_THETA, _THETA_RATE = ERROR.start, ERROR_RATE.start


def out_size(n: int) -> int:
    """`out`'s length for n cables: alpha_c and tau_c (6 each), then f0, the forces
    f_p, the tensions and the commands (n each)."""
    return 12 + 4 * n


@register_jitable  # plain Python here, compiled in the kernel: one layout for both
def out_parts(out: Array) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Views of `out`'s parts: (alpha_c, tau_c, f0, forces, tensions, commands)."""
    n = (out.shape[0] - 12) // 4
    return (out[0:6], out[6:12], out[12 : 12 + n], out[12 + n : 12 + 2 * n],
            out[12 + 2 * n : 12 + 3 * n], out[12 + 3 * n : 12 + 4 * n])  # fmt: skip


@njit(cache=True)
def command(
    K: Array,
    stack: Array,
    order: int,
    measured: Array,
    accel: Array,
    table: Array,
    G: Array,
    m0: Array,
    observed: Array,
    f_b: Array,
    t_ref: Array,
    low: Array,
    f_max: Array,
    f_scale: float,
    rtol: float,
    shortcut: bool,
    out: Array,
) -> bool:
    """The loop's sample on the pose error in `measured` (cdpr.measurement's out) into
    `stack` (the loop's, K and order its own), alpha_c = accel + its output, tau_c and
    f0 from the model (`table` = [Lambda | c], n x 7; `G`'s first 6 rows [M | mu]) less
    the `observed` wrench, into `out` (out_size); with `shortcut`, the least-norm
    tensions about t_ref: True when they meet every bound (t >= low, |f0 - t + f_b| <=
    f_max, within rtol of max(f_scale, ...)), the forces, tensions and commands then in
    `out` too.  False: the caller's solver decides from alpha_c, tau_c and f0 (the
    tensions' place in `out` then holds scratch)."""
    n = table.shape[0]
    for ch in range(6):
        stack[0, ch] = measured[_THETA + ch]
        if order > 1:
            stack[1, ch] = measured[_THETA_RATE + ch]
    loop = np.empty(6)
    advance(K, stack, order, loop)
    alpha, tau, f0, forces, t, commands = out_parts(out)
    for a in range(6):
        alpha[a] = accel[a] + loop[a]
    for a in range(6):
        s = 0.0
        for b in range(6):
            s += G[a, b] * alpha[b]
        tau[a] = s + G[a, 6] - observed[a]
    J = np.empty((n, 6))
    for k in range(n):
        s = 0.0
        for a in range(6):
            J[k, a] = table[k, a]
            s += table[k, a] * alpha[a]
        f0[k] = m0[k] * (s + table[k, 6])
    if not shortcut:
        return False
    C = np.zeros((6, 6))  # its factor: computed there (factored False)
    if not least_norm_inside(J, C, False, t_ref, tau, f_b, f0, low, f_max, f_scale, rtol, t):
        return False
    for k in range(n):
        forces[k] = f0[k] - t[k]
        commands[k] = forces[k] + f_b[k]
    return True
