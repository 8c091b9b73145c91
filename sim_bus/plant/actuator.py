"""The paper's Assumption 1 actuator model, realised as a state-space system.

Assumption 1 relates the command force f_c, the actual force f and the drum length l:

    C(s) f + K(s) l = C~(s) f_c,
    C(s) = 1 + c_2 s + ... + c_n s^(n-1),  K(s) = k_0 s + k_1 s^2 + ... + k_n s^(n+1),
    C~(s) = 1 + c~_2 s + ... + c~_p s^(p-1).

The drum (effective mass m0 in cable-length coordinates) obeys m0 l'' = f + w, with w
the cable tension minus friction.  K(s) may reach two derivatives beyond C(s), so it is
split by polynomial division, K(s)/s = Q(s) C(s) + R(s) with deg R < deg C and
Q(s) = q0 + q1 s, which gives

    f = f_in - q0 l' - q1 l'',   C(s) f_in = C~(s) f_c - R(s) l',

i.e. an extra viscous term q0 and an extra inertia q1 on the drum, and a proper system
from (f_c, l') to the "inner" force f_in with no feed-through from l'.  A model with
q0 < 0 (high-frequency force along the velocity: not passive) is refused.  Its observable
canonical realisation (A, B, C, D) is discretised exactly (zero-order hold on f_c and
l') with scipy.signal.cont2discrete, so the electrical lag never limits the step.
The default, c = (tau_e,) and k = (k0,), is tau_e f' + f = f_c - k0 l' (q0 = q1 = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ActuatorModel:
    """Continuous realisation: x' = A x + B [f_c, l'], f_in = C x + D [f_c, l'],
    the drum terms q0 (N s/m) and q1 (kg) of f = f_in - q0 l' - q1 l'', and the
    steady-state back-EMF k_0 (f = f_c - k_0 l' at constant l')."""

    A: Array
    B: Array
    C: Array
    D: Array
    q0: float
    q1: float
    back_emf: float

    @classmethod
    def realise(
        cls, C_poly: list[float], K_poly: list[float], Ct_poly: list[float]
    ) -> ActuatorModel:
        """Realise Assumption 1 from its polynomials in s, ascending (C(s), K(s)/s, C~(s):
        sim_bus.plant.config.ActuatorModelConfig.coefficients); ValueError for a model
        that is not passive at high frequency (q0 < 0)."""
        q, r = np.polynomial.polynomial.polydiv(K_poly, C_poly)  # ascending, exact
        Q = np.zeros(2)
        Q[: len(q)] = q
        R = np.zeros(len(C_poly) - 1)
        R[: min(len(r), len(R))] = r[: len(R)]
        if Q[0] < -1e-9:  # N s/m; a rounding-sized negative is harmless
            raise ValueError(
                f"k {K_poly} with c {C_poly[1:]} gives f = ... - q0 l' with q0 = {Q[0]:.6g} "
                "< 0, an actuator that pushes along its own velocity at high frequency; "
                "not supported (lower the last k or raise the last c)"
            )
        A, B, C, D = _observable_form(C_poly, [Ct_poly, [-c for c in R]])
        return cls(A, B, C, D, float(Q[0]), float(Q[1]), float(K_poly[0]))

    @property
    def order(self) -> int:
        """Number of states of the inner-force system."""
        return self.A.shape[0]

    def discretise(self, h: float) -> tuple[Array, Array, Array, Array]:
        """(Ad, Bd, C, D): exact zero-order-hold discretisation for step h."""
        if self.order == 0:
            return self.A, self.B, self.C, self.D
        Ad, Bd, Cd, Dd, _ = signal.cont2discrete((self.A, self.B, self.C, self.D), h, "zoh")
        return Ad, Bd, Cd, Dd

    def steady_state(self, command: float, rate: float) -> Array:
        """The state that constant f_c and l' hold still (A is invertible: C(0) = 1)."""
        if self.order == 0:
            return np.zeros(0)
        return -np.linalg.solve(self.A, self.B @ np.array([command, rate]))


def _observable_form(
    den: list[float], nums: list[list[float]]
) -> tuple[Array, Array, Array, Array]:
    """Observable canonical form of the one-output system y = sum_i nums[i](s)/den(s) u_i
    (ascending coefficients, deg nums[i] <= deg den)."""
    n = len(den) - 1
    lead = den[-1]
    a = np.array(den[:-1]) / lead  # monic: s^n + a[n-1] s^(n-1) + ... + a[0]
    A = np.zeros((n, n))
    if n:
        A[:, 0] = -a[::-1]
        A[: n - 1, 1:] = np.eye(n - 1)
    B = np.zeros((n, len(nums)))
    D = np.zeros((1, len(nums)))
    for i, num in enumerate(nums):
        b = np.zeros(n + 1)
        b[: len(num)] = np.array(num) / lead
        D[0, i] = b[n]
        B[:, i] = (b[:n] - b[n] * a)[::-1]
    C = np.zeros((1, n))
    if n:
        C[0, 0] = 1.0
    return A, B, C, D
