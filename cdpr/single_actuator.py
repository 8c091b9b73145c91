"""The single-actuator controller of the paper (§4) and its discretisation.

A continuous-time linear controller on the error vector eps = [e, e', ..., e^(l-1)]:

    x' = A x + B eps,    a = C x + D eps

(the paper's B sees e only; a B over the whole error vector is the general case and
lets a PID filter the measured rate instead of differentiating quantised positions).
PID is a = -(k_i int e + k_p e + k_d e').  One object is tuned on one actuator and
applied unchanged to each of the 6 tangent components of the robot (DESIGN §5): the
discrete form carries one state column per channel.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from cdpr.compiled_cache import key_numba_cache
from cdpr.wrench_observer import WrenchObserver

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]
Discretisation = Literal["zoh", "bilinear", "euler", "backward_diff"]


class LinearController:
    """Continuous-time (A, B, C, D) on the error vector [e, e', ...]: returns the
    control acceleration a (m/s^2 per metre of error, i.e. per unit mass)."""

    def __init__(self, A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike) -> None:
        D = np.atleast_2d(np.asarray(D, dtype=float))
        if D.shape[0] != 1 or D.shape[1] < 1:
            raise ValueError(f"D must be 1 x l (l = error derivatives used), got {D.shape}")
        order = D.shape[1]
        A = np.asarray(A, dtype=float).reshape(-1)
        n = round(float(np.sqrt(A.size)))
        if n * n != A.size:
            raise ValueError(f"A must be square, got {A.size} entries")
        A = A.reshape(n, n)
        B = np.asarray(B, dtype=float).reshape(n, order) if n else np.zeros((0, order))
        C = np.asarray(C, dtype=float).reshape(1, n) if n else np.zeros((1, 0))
        for name, m in (("A", A), ("B", B), ("C", C), ("D", D)):
            if not np.all(np.isfinite(m)):
                raise ValueError(f"controller matrix {name} has non-finite entries")
        if n and np.max(np.linalg.eigvals(A).real) > 1e-9:
            raise ValueError(
                f"controller matrix A is unstable (eigenvalues {np.linalg.eigvals(A)}); "
                "integrators (eigenvalue 0) are allowed"
            )
        self.A, self.B, self.C, self.D = A, B, C, D

    @property
    def order(self) -> int:
        """l: how many error derivatives (e, e', ...) the controller reads."""
        return self.D.shape[1]

    @property
    def states(self) -> int:
        return self.A.shape[0]

    def discretise(
        self, period: float, channels: int = 1, method: Discretisation = "zoh"
    ) -> DiscreteController:
        """The controller for a loop period (s), with `channels` independent state
        columns (6 for the robot's tangent components, 1 for one actuator)."""
        if not period > 0.0:
            raise ValueError(f"period must be positive, got {period}")
        if self.states == 0:
            Ad, Bd = np.zeros((0, 0)), np.zeros((0, self.order))
            Cd, Dd = self.C, self.D
        else:
            Ad, Bd, Cd, Dd, _ = signal.cont2discrete(
                (self.A, self.B, self.C, self.D), period, method=method
            )
        return DiscreteController(Ad, Bd, Cd, Dd, channels)

    def frequency_response(self, s: complex | Array) -> Array:
        """Controller gains per error derivative at Laplace variable s: the row
        C (sI - A)^-1 B + D, shape (..., l), for loop analysis."""
        s = np.asarray(s, dtype=complex)
        out = np.empty((*s.shape, self.order), dtype=complex)
        eye = np.eye(self.states)
        for idx, sv in np.ndenumerate(s):
            row = self.D[0].astype(complex)
            if self.states:
                row = row + (self.C @ np.linalg.solve(sv * eye - self.A, self.B))[0]
            out[idx] = row
        return out


def pid(
    kp: float, ki: float = 0.0, kd: float = 0.0, derivative_filter: float = 0.0
) -> LinearController:
    """a = -(ki int e + kp e + kd e'_f), gains per unit mass (1/s^2, 1/s^3, 1/s).

    e' is the measured error rate; with derivative_filter = T_f > 0 it passes a
    first-order low-pass e'_f' = (e' - e'_f) / T_f first (encoder rates are noisy).
    """
    gains = {"kp": kp, "ki": ki, "kd": kd, "derivative_filter": derivative_filter}
    for name, value in gains.items():
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"PID {name} must be a finite number >= 0, got {value}")
    filtered = derivative_filter > 0.0 and kd > 0.0
    A: list[list[float]] = []
    B: list[list[float]] = []
    C: list[float] = []
    size = (ki > 0.0) + filtered
    if ki:
        A.append([0.0] * size)
        B.append([1.0, 0.0])
        C.append(-ki)
    if filtered:
        A.append([0.0] * (size - 1) + [-1.0 / derivative_filter])
        B.append([0.0, 1.0 / derivative_filter])
        C.append(-kd)
    return LinearController(A, B, C, [[-kp, 0.0 if filtered else -kd]])


class DiscreteController:
    """x[k+1] = Ad x[k] + Bd eps[k],  a[k] = Cd x[k] + Dd eps[k], for several channels
    at once: eps is l x channels, the state nx x channels, a has one entry per channel."""

    def __init__(self, Ad: Array, Bd: Array, Cd: Array, Dd: Array, channels: int) -> None:
        self.Ad, self.Bd, self.Cd, self.Dd = Ad, Bd, Cd, Dd
        self.channels = channels
        self._order = Dd.shape[1]
        # [a; x[k+1]] = K [eps[k]; x[k]]: one matrix product per sample (per-call numpy
        # overhead dominates at this size); the state is the lower rows of that stack
        self._K = np.block([[Dd, Cd], [Bd, Ad]])
        self._stack = np.zeros((self._order + Ad.shape[0], channels))
        self.state = self._stack[self._order :]  # a view: (states, channels)
        # numba loads the kernel at its first call: here, not in a control cycle
        advance(self._K, self._stack.copy(), self._order, np.empty(channels))
        self._hold = _hold_direction(Ad, Cd)

    def hand_over(self, delta: Array) -> None:
        """Move each channel's output by `delta` without an error to cause it, as far as
        the integrators hold output of the opposite sign (never past zero): when a better
        model takes over what the integral action held.  The integrators' state is the one
        that holds a constant output at zero error (Ad v = v); nothing moves without one."""
        if self._hold is None:
            return
        held = self._hold[1].dot(self.state)  # per channel, the output the integrators hold
        take = np.where(delta * held < 0.0, np.sign(delta) * np.minimum(abs(delta), abs(held)), 0)
        self.take_on(take)

    def take_on(self, delta: Array) -> None:
        """Move each channel's output by `delta` without an error to cause it, whatever
        the sign: the integrators take on what something else held until now (nothing
        moves without them)."""
        if self._hold is not None:
            self.state += np.outer(self._hold[0], delta)

    def reset(self) -> None:
        """Zero the state (integrators, filters): on enable and after a brake."""
        self.state[:] = 0.0

    def preset(self, output: Array) -> None:
        """Zero the state but for the integrators, which hold `output` per channel at zero
        error (a bumpless start where something else carried part of the load);
        ValueError without integral action."""
        if self._hold is None:
            raise ValueError("the controller has no integral action to hold an output")
        self.state[:] = np.outer(self._hold[0], output)

    def step(self, error: Array) -> Array:
        """One sample: `error` is l x channels ([e; e'; ...]); returns a (channels,)."""
        self._stack[: self._order] = error
        out = np.empty(self.channels)
        advance(self._K, self._stack, self._order, out)
        return out

    def kernel_terms(self) -> tuple[Array, Array, int]:
        """(K, the stack [eps; x], l) for a compiled caller that writes the error into the
        stack's first l rows and calls `advance` itself."""
        return self._K, self._stack, self._order


@njit(cache=True)
def advance(K: Array, stack: Array, order: int, output: Array) -> None:
    """One sample of DiscreteController on `stack` = [eps[k]; x[k]] (the error in its
    first `order` rows): output = a[k], and x[k+1] into the stack's lower rows, by
    [a; x[k+1]] = K [eps; x] (one product: per-call numpy overhead dominated)."""
    rows, cols, channels = K.shape[0], K.shape[1], stack.shape[1]
    new = np.empty((rows, channels))
    for r in range(rows):
        for ch in range(channels):
            s = 0.0
            for q in range(cols):
                s += K[r, q] * stack[q, ch]
            new[r, ch] = s
    for ch in range(channels):
        output[ch] = new[0, ch]
    for r in range(1, rows):
        for ch in range(channels):
            stack[order + r - 1, ch] = new[r, ch]


def _hold_direction(Ad: Array, Cd: Array) -> tuple[Array, Array] | None:
    """A state direction v with Ad v = v (an integrator's) scaled to Cd v = 1, and the
    left eigenvector w (w Ad = w, w v = 1) that reads the state's component along it;
    None without one."""
    if Ad.shape[0] == 0:
        return None
    values, vectors = np.linalg.eig(Ad)
    left_values, left_vectors = np.linalg.eig(Ad.T)
    for k in np.flatnonzero(np.abs(values - 1.0) < 1e-9):
        v = np.real(vectors[:, k])
        gain = float(Cd.reshape(-1).dot(v))
        j = int(np.argmin(np.abs(left_values - 1.0)))
        w = np.real(left_vectors[:, j])
        if abs(gain) > 1e-12 and abs(float(w.dot(v))) > 1e-12:
            return v / gain, w * gain / float(w.dot(v))
    return None


class SingleActuatorTracker:
    """The paper's closed-loop feed-forward controller for ONE actuator with effective
    mass m (§4): f_c = m (l_r'' + a) + k0 l_r' + bias, a from the discrete controller on
    [l - l_r, l' - l_r'].  `bias` is the known static load (e.g. -preload on the rig).
    It is how the gains are tuned and checked on a single actuator.  With an `observer`
    (cdpr.wrench_observer, size 1) the force the model does not explain is estimated
    and cancelled, as on the robot; `lead` (s) is when a command acts after its
    measurement (the drive's force lag and half a period)."""

    def __init__(
        self,
        controller: LinearController,
        period: float,
        mass: float,
        k0: float,
        bias: float = 0.0,
        method: Discretisation = "zoh",
        observer: WrenchObserver | None = None,
        lead: float = 0.0,
    ) -> None:
        if controller.order > 2:
            raise ValueError("the tracker measures e and e' only (controller order <= 2)")
        if not 0.0 < mass < np.inf:
            raise ValueError(f"mass must be positive and finite, got {mass}")
        self.loop = controller.discretise(period, 1, method)
        self.mass, self.k0, self.bias = float(mass), float(k0), float(bias)
        self.observer, self.lead = observer, lead
        self._error = np.zeros((controller.order, 1))

    def command(
        self, length: float, rate: float, ref_length: float, ref_rate: float, ref_accel: float
    ) -> float:
        """The force command (N) for this sample."""
        self._error[0, 0] = length - ref_length
        if self._error.shape[0] > 1:
            self._error[1, 0] = rate - ref_rate
        a = float(self.loop.step(self._error)[0])
        net = self.mass * (ref_accel + a)
        if self.observer is not None:
            net -= float(self.observer.estimate[0])
            self.observer.update(np.array([rate]), np.array([[self.mass]]), np.array([net]),
                                 self.lead)  # fmt: skip
        return net + self.k0 * ref_rate + self.bias
