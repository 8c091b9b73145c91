"""Tension distribution F and the wrench-set membership test W (DESIGN §6).

Given the Jacobian Λ (n × 6), the wrench τ, the back-EMF forces f_b and the no-load
forces f0, find the actuator forces f with

    Λᵀ f = τ,    t = f0 − f ≥ t_min,    |f + f_b| ≤ force_max     (per cable),

whose tensions t are closest to a reference t_ref (minimise ‖t − t_ref‖²).  Both solvers
work in tension space, where the problem is a projection onto a box-bounded affine set:

    Λᵀ t = w := Λᵀ f0 − τ,        t_lo ≤ t ≤ t_hi,
    t_lo = max(t_min, f0 + f_b − force_max),    t_hi = f0 + f_b + force_max,

and report f = f0 − t.  (τ, f_b, f0) ∈ W exactly when ``solve`` returns feasible=True.

With a tension floor (TensionLimits.floor > 0) the distribution first asks every cable
for t_min + floor and only where no tensions meet that for t_min itself: a drive's
cable tension departs from its command by the winch's unmodelled dynamics, and a cable
commanded at t_min exactly dips below it.  W is still the set at t_min.

Every answer is CHECKED before it is called feasible: with
``tol = rtol · max(max force_max, max t_hi)`` (rtol = 1e-6 by default: 0.6 mN on the
600 N reference robot), the wrench residual ‖Λᵀ t − w‖∞ ≤ tol and
t_lo − tol ≤ t ≤ t_hi + tol.  Anything else is infeasible with a reason naming the
violated constraint, the cable and the values.

Inside the control cycle nothing raises for bad numbers: a NaN or inf input gives
feasible=False with reason "non-finite input: <name>" (and never reaches OSQP).  Wrong
shapes are programming errors and raise ValueError naming the argument.

Infeasible results carry a best attempt: finite whenever all inputs were finite (the
solver's last iterate, or, when OSQP declared the problem infeasible and its iterate is
meaningless, the least-norm tensions around t_ref that satisfy the wrench equality but
ignore the bounds); all-NaN only for a non-finite input.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np
import osqp
import scipy.sparse as sp
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dposv

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import F64, cholesky, cholesky_solve, gram, kernel_array

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

if TYPE_CHECKING:
    from cdpr.robot import Robot

Array = NDArray[np.float64]

METHODS = ("osqp", "closed_form")
DEFAULT_RTOL = 1e-6  # check tolerance relative to the force scale (see module docstring)
_RANK_RTOL = 1e-6  # Cholesky pivot ratio below which a (reduced) Jacobian counts as rank deficient
_CERT_RTOL = 1e-3  # certificate entries this small relative to the largest are not named
_COMPONENTS = ("force x", "force y", "force z", "torque x", "torque y", "torque z")


class TensionResult(NamedTuple):
    """Outcome of F: forces f, tensions t = f0 − f, whether (τ, f_b, f0) ∈ W and why not.

    ``reason`` is "" when feasible.  ``iterations`` counts OSQP iterations (0 for the
    closed form).  For infeasible results see the module docstring on best attempts.
    """

    forces: Array
    tensions: Array
    feasible: bool
    reason: str = ""
    iterations: int = 0


@dataclass(frozen=True, eq=False)
class TensionLimits:
    """Per-cable tension limits: t ≥ t_min, |f + f_b| ≤ force_max, reference tension t_ref,
    and the `floor` (N) above t_min the distribution keeps each cable where it can (module
    docstring).

    Arrays of length n (converted to read-only float arrays).  Requires
    0 ≤ t_min ≤ t_ref ≤ force_max, force_max > 0 for every cable and a finite floor ≥ 0.
    """

    t_min: Array
    force_max: Array
    t_ref: Array
    floor: float = 0.0

    def __post_init__(self) -> None:
        for name in ("t_min", "force_max", "t_ref"):
            raw = getattr(self, name)
            try:
                a = np.array(raw, dtype=float)
            except (TypeError, ValueError) as exc:
                msg = f"TensionLimits.{name} is not an array of numbers: {exc}"
                raise ValueError(msg) from None
            if a.ndim != 1 or a.size == 0:
                raise ValueError(
                    f"TensionLimits.{name} needs one value per cable (a 1-d array), "
                    f"got shape {a.shape}"
                )
            if not np.all(np.isfinite(a)):
                raise ValueError(f"TensionLimits.{name} has non-finite values: {a.tolist()}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        try:
            floor = float(self.floor)
        except (TypeError, ValueError):
            floor = math.nan
        if not (math.isfinite(floor) and floor >= 0.0):
            raise ValueError(f"TensionLimits.floor must be a number >= 0, got {self.floor!r}")
        object.__setattr__(self, "floor", floor)
        n = self.t_min.size
        for name in ("force_max", "t_ref"):
            m = getattr(self, name).size
            if m != n:
                raise ValueError(
                    f"TensionLimits.{name} has {m} values but t_min has {n} (one per cable)"
                )
        for k, (t_min, f_max, t_ref) in enumerate(
            zip(self.t_min.tolist(), self.force_max.tolist(), self.t_ref.tolist(), strict=True)
        ):
            if t_min < 0.0:
                raise ValueError(f"cable {k}: t_min {t_min:g} N is negative (cables cannot push)")
            if f_max <= 0.0:
                raise ValueError(f"cable {k}: force_max {f_max:g} N must be positive")
            if t_min > f_max:
                raise ValueError(f"cable {k}: t_min {t_min:g} N exceeds force_max {f_max:g} N")
            if not t_min <= t_ref <= f_max:
                raise ValueError(
                    f"cable {k}: t_ref {t_ref:g} N outside [t_min {t_min:g} N, "
                    f"force_max {f_max:g} N]"
                )

    @property
    def n(self) -> int:
        """Number of cables."""
        return int(self.t_min.size)

    @classmethod
    def from_robot(
        cls, robot: Robot, t_ref: ArrayLike | float | None = None, floor: float = 0.0
    ) -> TensionLimits:
        """Limits from the robot's actuators; t_ref defaults to mid-range (t_min + force_max)/2.

        A scalar t_ref applies to every cable.
        """
        t_min = np.asarray(robot.t_min, dtype=float)
        force_max = np.asarray(robot.force_max, dtype=float)
        if t_ref is None:
            ref = 0.5 * (t_min + force_max)
        elif np.ndim(t_ref) == 0:
            ref = np.full(t_min.shape, float(t_ref))
        else:
            ref = np.asarray(t_ref, dtype=float)
        return cls(t_min, force_max, ref, floor)


class Shortcut(NamedTuple):
    """A solver's least-norm shortcut as least_norm_inside takes it (the kernels' copies:
    writable float64, never written)."""

    t_ref: Array
    low: Array  # the first lower bound solve() tries: t_min (+ floor)
    f_max: Array
    f_scale: float
    rtol: float


class FactoredJacobian(NamedTuple):
    """A Jacobian Λ (contiguous, n × 6) with what the least-norm tensions need of it
    alone: the Cholesky factor of ΛᵀΛ (cdpr.compiled_linalg.cholesky's; None where
    singular) and t_refᵀΛ.  From a solver's ``factored``; its ``solve`` takes it in
    place of Λ."""

    jacobian: Array
    factor: Array | None
    t_ref_dot: Array


class TensionSolver(Protocol):
    """What the controller needs of a tension distribution method."""

    method: str
    limits: TensionLimits

    def solve(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
    ) -> TensionResult: ...

    def factored(self, jacobian: ArrayLike) -> FactoredJacobian: ...

    def shortcut(self) -> Shortcut | None: ...

    def answered_inside(self, t: Array) -> None: ...


def make_tension_solver(method: str, limits: TensionLimits, **options: Any) -> TensionSolver:
    """The solver named in the config: "osqp" or "closed_form"; options go to its constructor."""
    if method == "osqp":
        return OsqpTensionSolver(limits, **options)
    if method == "closed_form":
        return ClosedFormTensionSolver(limits, **options)
    raise ValueError(
        f"unknown tension distribution method {method!r}; allowed: "
        + ", ".join(repr(m) for m in METHODS)
    )


_Low = tuple[Array, list[float]]  # lower tension bounds, as an array and as a list


class _Problem(NamedTuple):
    """One cycle's data in tension space."""

    L: Array  # Jacobian, n x 6
    f0: Array
    w: Array  # Λᵀ f0 − τ
    g: Array  # f0 + f_b
    lo: Array  # t_lo
    hi: Array  # t_hi
    tol: float
    factored: FactoredJacobian | None  # L's, when solve was given them


class _TensionSolverBase:
    """Input validation, the tension-space data, and the final constraint check."""

    method = ""

    def __init__(self, limits: TensionLimits, rtol: float = DEFAULT_RTOL) -> None:
        if not isinstance(limits, TensionLimits):
            raise TypeError(f"limits must be a TensionLimits, got {type(limits).__name__}")
        if not (math.isfinite(rtol) and rtol > 0.0):
            raise ValueError(f"rtol must be a positive number, got {rtol!r}")
        self.limits = limits
        self.n = limits.n
        self.rtol = float(rtol)
        self._t_min = limits.t_min
        # the lower tension bounds to try, in order (array, list): t_min + floor first
        # when there is a floor
        bounds = [limits.t_min + limits.floor] if limits.floor > 0.0 else []
        self._lows = [(b, b.tolist()) for b in (*bounds, limits.t_min)]
        self._f_max = limits.force_max
        self._t_ref = limits.t_ref
        self._f_scale = float(limits.force_max.max())
        self._nan = np.full(self.n, np.nan)
        self._nan.setflags(write=False)
        self._shortcut = True  # whether the least-norm tensions are tried first (_inside)
        # writable copies for the kernel (a read-only array is another type to numba)
        self._kernel_lows = [np.array(low) for low, _ in self._lows]
        self._kernel_f_max, self._kernel_t_ref = np.array(self._f_max), np.array(self._t_ref)
        self._load_kernels()

    def _load_kernels(self) -> None:
        """Call the kernels solve() runs, once, here: numba loads (or compiles) each at
        its first call, which must not be a control cycle's."""
        J = np.eye(self.n, 6)
        factored = self._factor(J)
        self._least_norm(J, np.zeros(6), factored)
        zero = np.zeros(self.n)
        self._inside(factored, np.zeros(6), zero, zero, self._kernel_lows[0])

    def solve(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
    ) -> TensionResult:
        """F(τ, f_b, f0) at Jacobian Λ (n × 6, or factored(Λ)); feasible only after the
        constraint check.

        Raises ValueError only for wrong shapes; NaN/inf give an infeasible result, and
        numpy's floating-point warnings are silenced so they cannot turn into exceptions.
        Most cycles end in _inside: the least-norm tensions meet every bound.
        """
        for low, kernel_low in zip(self._lows, self._kernel_lows, strict=True):
            if self._shortcut:
                inside = self._inside(jacobian, wrench, f_b, f0, kernel_low)
                if inside is not None:
                    return inside
            with np.errstate(all="ignore"):
                result = self._solve(jacobian, wrench, f_b, f0, low)
            if result.feasible:
                break
        return result

    def factored(self, jacobian: ArrayLike) -> FactoredJacobian:
        """Λ with what the least-norm tensions need of it alone (FactoredJacobian), for
        solve() in Λ's place: a control cycle computes it before the measurement."""
        L = np.ascontiguousarray(_checked(jacobian, (self.n, 6), "jacobian"))
        with np.errstate(all="ignore"):
            return self._factor(L)

    def _factor(self, L: Array) -> FactoredJacobian:
        """factored() of a checked, contiguous Λ."""
        factor = np.zeros((6, 6))
        positive = _gram_factor(kernel_array(L, (self.n, 6)), factor)
        return FactoredJacobian(L, factor if positive else None, self._t_ref.dot(L))

    def _inside(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
        low: Array,
    ) -> TensionResult | None:
        """The answer when the least-norm tensions about t_ref meet every bound with
        tensions at least `low` (checked as _check checks: then they are the QP's
        optimum, and Pott's method's first solve); None for the method's own path to
        decide (a bound active, a non-finite or singular input, a wrong shape)."""
        n = self.n
        if type(jacobian) is FactoredJacobian:
            J, C = jacobian.jacobian, jacobian.factor
            if C is not None:  # read-only, kept for a reference at rest
                C = kernel_array(C, (6, 6))
        else:
            J, C = jacobian, None
        J = kernel_array(J, (n, 6))
        tau, fb, f0 = kernel_array(wrench, (6,)), kernel_array(f_b, (n,)), kernel_array(f0, (n,))
        if J is None or tau is None or fb is None or f0 is None:
            return None
        t = np.empty(n)
        factored = C is not None
        if not least_norm_inside(J, C if factored else _NO_FACTOR, factored, self._kernel_t_ref,
                                 tau, fb, f0, low, self._kernel_f_max, self._f_scale, self.rtol,
                                 t):  # fmt: skip
            return None
        self.answered_inside(t)
        return TensionResult(f0 - t, t, True, "", 0)

    def shortcut(self) -> Shortcut | None:
        """What a compiled caller passes least_norm_inside to try the least-norm tensions
        itself, as solve() tries them first (then answered_inside); None where this
        solver does not (OSQP's interior_shortcut=False)."""
        if not self._shortcut:
            return None
        return Shortcut(self._kernel_t_ref, self._kernel_lows[0], self._kernel_f_max,
                        self._f_scale, self.rtol)  # fmt: skip

    def answered_inside(self, t: Array) -> None:
        """What a method keeps of least-norm tensions `t` that met every bound, the cycle's
        answer (OSQP: its next warm start)."""

    def _solve(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
        low: _Low,
    ) -> TensionResult:
        """F with tensions at least `low` (one of _lows)."""
        raise NotImplementedError

    def _prepare(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
        low: _Low,
        out: tuple[Array, Array, Array] | None = None,
    ) -> _Problem | TensionResult:
        """Validated tension-space data with tensions at least `low`, or an infeasible
        result that needs no solver.

        ``out`` = (w, t_lo, t_hi) buffers to compute into (OSQP's l and u), else new arrays.
        """
        n = self.n
        factored = None
        if type(jacobian) is FactoredJacobian:
            factored, L = jacobian, jacobian.jacobian
        else:
            # contiguous, and products with ndarray.dot: see the cdpr.kinematics docstring
            L = np.ascontiguousarray(_checked(jacobian, (n, 6), "jacobian"))
        tau = _checked(wrench, (6,), "wrench")
        fb = _checked(f_b, (n,), "f_b")
        f0 = _checked(f0, (n,), "f0")
        w_out, lo_out, hi_out = (None, None, None) if out is None else out
        w = np.subtract(f0.dot(L), tau, out=w_out)
        g = f0 + fb
        f_max = self._f_max
        hi = np.add(g, f_max, out=hi_out)
        hi_list = hi.tolist()
        # any NaN/inf input makes w or t_hi non-finite (inf * 0 is NaN): one test on the hot path
        if not math.isfinite(sum(w.tolist()) + sum(hi_list)):
            return self._non_finite(L, tau, fb, f0)
        low_array, low_list = low
        lo = np.maximum(low_array, g - f_max, out=lo_out)
        if any(map(operator.lt, hi_list, low_list)):  # t_lo > t_hi somewhere
            k = max(range(n), key=lambda i: low_list[i] - hi_list[i])
            reason = (
                f"cable {k}: t_min {low_list[k]:.4g} N unreachable, the actuator holds "
                f"at most f0 + f_b + force_max = {hi_list[k]:.4g} N"
            )
            t = self._least_norm(L, w, factored)
            return TensionResult(f0 - t, t, False, reason, 0)
        tol = self.rtol * max(self._f_scale, *hi_list)
        return _Problem(L, f0, w, g, lo, hi, tol, factored)

    def _non_finite(self, L: Array, tau: Array, fb: Array, f0: Array) -> TensionResult:
        for name, value in (("jacobian", L), ("wrench", tau), ("f_b", fb), ("f0", f0)):
            if not np.all(np.isfinite(value)):
                reason = f"non-finite input: {name}"
                break
        else:
            reason = "non-finite intermediate values: inputs too large"
        return TensionResult(self._nan.copy(), self._nan.copy(), False, reason, 0)

    def _check(self, p: _Problem, t: Array) -> str:
        """Empty if t satisfies the constraints within p.tol, else the worst violation."""
        residual = (t.dot(p.L) - p.w).tolist()
        viol = np.maximum(p.lo - t, t - p.hi).tolist()  # > 0 outside [t_lo, t_hi]
        if not math.isfinite(sum(residual) + sum(viol)):
            return "non-finite tensions"
        e = max(map(abs, residual))
        if e > p.tol:
            j = [abs(r) for r in residual].index(e)
            return (
                f"wrench equality residual {e:.3g} ({_COMPONENTS[j]}) exceeds tolerance {p.tol:.3g}"
            )
        v = max(viol)
        if v > p.tol:
            return self._describe(viol.index(v), p, float(t[viol.index(v)]))
        return ""

    def _describe(self, k: int, p: _Problem, t: float) -> str:
        """Name the bound that tension t of cable k violates (t_lo is t_min or force_max)."""
        t_min = float(self._t_min[k])
        f_max = float(self._f_max[k])
        act = float(p.g[k]) - t  # f + f_b
        if t < float(p.lo[k]) and t_min >= float(p.g[k]) - f_max:
            return f"cable {k} tension {t:.4g} N below t_min {t_min:.4g} N"
        return (
            f"cable {k} actuator force |f + f_b| = {abs(act):.4g} N exceeds force_max "
            f"{f_max:.4g} N (tension {t:.4g} N)"
        )

    def _least_norm(self, L: Array, w: Array, factored: FactoredJacobian | None) -> Array:
        """Tensions nearest t_ref that satisfy Λᵀ t = w, bounds ignored: the QP's optimum
        when they meet every bound, else a finite attempt.  One 6 × 6 Cholesky (done
        already in `factored`, L's, if given); a least-squares fallback where Λ is rank
        deficient."""
        if factored is None:
            factored = self._factor(L)
        rhs = w - factored.t_ref_dot
        if factored.factor is not None:
            cholesky_solve(kernel_array(factored.factor, (6, 6)), rhs)
            return self._t_ref + L.dot(rhs)
        return self._t_ref + np.linalg.lstsq(L.T, rhs, rcond=None)[0]

    def _result(self, p: _Problem, t: Array, reason: str, iterations: int) -> TensionResult:
        return TensionResult(p.f0 - t, t, not reason, reason, iterations)


_NO_FACTOR = np.zeros((6, 6))


@njit(cache=True)
def _gram_factor(J: Array, C: Array) -> bool:
    """C = the Cholesky factor of J^T J (cdpr.compiled_linalg.cholesky); False where it
    is singular."""
    G = np.empty((6, 6))
    gram(J.T, G)
    return cholesky(G, C)


@njit(cache=True)
def least_norm_inside(
    J: Array,
    C: Array,
    factored: bool,
    t_ref: Array,
    tau: Array,
    f_b: Array,
    f0: Array,
    low: Array,
    f_max: Array,
    f_scale: float,
    rtol: float,
    t: Array,
) -> bool:
    """t = the least-norm tensions about t_ref with J^T t = w = J^T f0 - tau (C: the
    factor of J^T J when `factored`, else computed here); True when every tension lies
    in [t_lo, t_hi] (t_lo = max(low, f0 + f_b - f_max), t_hi = f0 + f_b + f_max) and the
    wrench holds, within tol = rtol max(f_scale, max t_hi) as _check's; False also for
    anything not finite, t_lo > t_hi or a singular J^T J."""
    n = J.shape[0]
    w = np.empty(6)
    top = f_scale
    total = 0.0  # any NaN or inf input makes w or a t_hi non-finite (inf * 0 is NaN)
    for k in range(n):
        hi = f0[k] + f_b[k] + f_max[k]
        if not hi >= low[k]:  # unreachable
            return False
        top = max(top, hi)
        total += hi
    for a in range(6):
        s = -tau[a]
        for k in range(n):
            s += f0[k] * J[k, a]
        w[a] = s
        total += s
    if not math.isfinite(total):
        return False
    if not factored:
        C = np.zeros((6, 6))
        if not _gram_factor(J, C):
            return False
    x = np.empty(6)
    for a in range(6):
        s = w[a]
        for k in range(n):
            s -= t_ref[k] * J[k, a]
        x[a] = s
    cholesky_solve(C, x)
    tol = rtol * top
    for k in range(n):
        s = t_ref[k]
        for a in range(6):
            s += J[k, a] * x[a]
        t[k] = s
        g = f0[k] + f_b[k]
        lo = max(low[k], g - f_max[k])
        if not (lo - s <= tol and s - (g + f_max[k]) <= tol):
            return False
    for a in range(6):
        s = -w[a]
        for k in range(n):
            s += t[k] * J[k, a]
        if not abs(s) <= tol:
            return False
    return True


def _checked(x: ArrayLike, shape: tuple[int, ...], name: str) -> Array:
    """x as a float64 array of the given shape; ValueError naming the argument otherwise."""
    if type(x) is not np.ndarray or x.dtype is not F64:
        try:
            x = np.asarray(x, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} is not an array of numbers: {exc}") from None
    if x.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {x.shape}")
    return x


# -- OSQP ------------------------------------------------------------------------------

_SOLVED = int(osqp.SolverStatus.OSQP_SOLVED)
# worth one tighter re-solve: not polished, failed the check, or inaccurate.  Not
# "maximum iterations reached": that happens near the boundary of W, where a re-solve
# mostly burns another max_iter iterations; such a run gets one cold start instead (a
# warm start from a far-off problem can stall ADMM inside W: 1 of 300 random problems
# of tests/cdpr/test_tension.py, 33 N inside W, on an AMD EPYC host).
_RETRYABLE = {_SOLVED, int(osqp.SolverStatus.OSQP_SOLVED_INACCURATE)}
_PRIMAL_INFEASIBLE = {
    int(osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE),
    int(osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE),
}
_POLISH_OK = 1
_MAX_ITER = int(osqp.SolverStatus.OSQP_MAX_ITER_REACHED)
ADAPTIVE_RHO_INTERVAL = 5  # iterations: as often as check_termination (its default 5)
_UPDATE_REJECTED = -1000  # our own status: osqp refused the data update


class OsqpTensionSolver(_TensionSolverBase):
    """F by OSQP: set up once with a fixed sparsity pattern, values updated each cycle.

    Variables are the tensions t; P = I, q = −t_ref (constant), and the constraint matrix
    A = [Λᵀ; I] is stored column by column (cable k: rows 0..5 hold Λ[k], row 6 + k the
    box) with its pattern built explicitly, so exact zeros in Λ (symmetric poses) keep
    their slots.  Each ``solve`` updates A's values and (l, u), then solves warm-started
    with polishing.  When polishing fails or the check fails, the same problem is solved
    once more, warm-started, with eps_abs = eps_rel = refine_eps (ADMM alone then meets the
    check); that is rare (a few per thousand cycles with active bounds).

    ``interior_shortcut=True`` first computes the equality-constrained optimum around
    t_ref (one 6 × 6 Cholesky); when it satisfies every bound (checked as always) it is
    the QP's optimum and OSQP is not called (iterations 0); OSQP solves the cycles where
    a bound is active.

    ``direct=True`` drives the compiled solver object (``OSQP()._solver``) directly,
    ≈ 15 µs faster per call than osqp's Python ``update``/``solve`` wrappers, which are
    used instead when ``direct=False`` or when the installed osqp lacks that object.

    osqp 1.1.3 behaviour relied on here: a data update it rejects (l > u, or fewer A values
    than the pattern) returns nonzero, prints to stdout and keeps the OLD data, so return
    codes are checked and l ≤ u is ensured beforehand; on primal infeasibility x is finite
    garbage (not NaN), so the certificate is used for the reason instead.  Scaling 1 (one
    Ruiz pass) suffices because A = [Λᵀ; I] and P = I are O(1) by construction; it makes the
    per-cycle matrix update cheaper than osqp's default of 10.
    """

    method = "osqp"

    def __init__(
        self,
        limits: TensionLimits,
        *,
        eps_abs: float = 1e-6,
        eps_rel: float = 1e-3,
        refine_eps: float = 1e-7,
        max_iter: int = 4000,
        check_termination: int = 5,
        scaling: int = 1,
        rtol: float = DEFAULT_RTOL,
        direct: bool = True,
        interior_shortcut: bool = True,
    ) -> None:
        super().__init__(limits, rtol)
        self.interior_shortcut = self._shortcut = interior_shortcut
        n = self.n
        self._eps = (float(eps_abs), float(eps_rel))
        self._refine_eps = float(refine_eps)
        # A's values, in CSC order: row k of this buffer is column k of A, [Λ[k, :], 1]
        self._Ax = np.ones((n, 7))
        self._Ax_flat = self._Ax.reshape(-1)  # a view: writing _Ax updates it
        rows = np.concatenate([np.arange(6)[None, :].repeat(n, 0), 6 + np.arange(n)[:, None]], 1)
        A = sp.csc_matrix(
            (self._Ax_flat.copy(), rows.reshape(-1), np.arange(0, 7 * n + 1, 7)),
            shape=(6 + n, n),
        )
        P = sp.csc_matrix((np.ones(n), np.arange(n), np.arange(n + 1)), shape=(n, n))
        assert A.nnz == 7 * n and A.has_sorted_indices
        self._l = np.zeros(6 + n)
        self._u = np.zeros(6 + n)
        self._l[6:] = self._t_min
        self._u[6:] = self._f_max
        self._y0 = np.zeros(6 + n)
        self._out = (self._l[:6], self._l[6:], self._u[6:])  # views: _prepare writes l, u
        prob = osqp.OSQP()
        prob.setup(
            P,
            -self._t_ref,
            A,
            self._l,
            self._u,
            eps_abs=self._eps[0],
            eps_rel=self._eps[1],
            max_iter=int(max_iter),
            check_termination=int(check_termination),
            scaling=int(scaling),
            polishing=True,
            warm_starting=True,
            adaptive_rho=True,
            # every 5 iterations; osqp's default (0) times its set-up and adapts rho as
            # often as that took: a different run on a busy host, and on some problems
            # rho ran away (to 5e4 or 0) and ADMM stalled inside W (8,000 iterations,
            # 1.9 N inside; solved in 320 with a fixed interval, and the control cycle's
            # median 5 iterations as before: bench/tension.py)
            adaptive_rho_interval=ADAPTIVE_RHO_INTERVAL,
            verbose=False,
        )
        self._prob = prob
        solver = getattr(prob, "_solver", None) if direct else None
        needed = ("update_data_vec", "update_data_mat", "solve", "update_settings", "warm_start")
        self._solver = solver if all(hasattr(solver, a) for a in needed) else None
        self.direct = self._solver is not None
        self._last: Any = None  # the last solution object (x, prim_inf_cert)
        self._info: Any = None  # the last solve's info (status, iter, ...)
        self._start: Array | None = None  # tensions to warm-start the next OSQP run from

    def _solve(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
        low: _Low,
    ) -> TensionResult:
        p = self._prepare(jacobian, wrench, f_b, f0, low, self._out)
        if type(p) is TensionResult:
            return p
        assert isinstance(p, _Problem)
        self._Ax[:, :6] = p.L
        self._u[:6] = p.w  # l[:6] = w, l[6:] = t_lo and u[6:] = t_hi are written by _prepare
        x, status, polish, iterations = self._run()
        if status == _SOLVED and polish == _POLISH_OK:
            reason = self._check(p, x)
            if not reason:
                return TensionResult(p.f0 - x, x, True, "", iterations)
        return self._retry(p, x, status, iterations)

    def _retry(self, p: _Problem, x: Array, status: int, iterations: int) -> TensionResult:
        """Slow path: refine a solution that was not polished or not checked, or report why."""
        if status == _MAX_ITER:  # once more from the reference tensions (cold start)
            self._warm_start(self._t_ref)
            x, status, polish, more = self._run(self._eps[0])
            iterations += more
            if status == _SOLVED and polish == _POLISH_OK and not self._check(p, x):
                return TensionResult(p.f0 - x, x, True, "", iterations)
        if status in _RETRYABLE:
            x, status, _, more = self._run(self._refine_eps)
            iterations += more
            if status == _SOLVED:
                return self._result(p, x, self._check(p, x), iterations)
        if status in _PRIMAL_INFEASIBLE:
            reason = self._infeasibility_reason(p)
            x = self._least_norm(p.L, p.w, p.factored)
        elif status == _UPDATE_REJECTED:
            reason = "osqp rejected the data update"
            x = self._least_norm(p.L, p.w, p.factored)
        else:
            reason = f"solver status: {self._info.status} after {iterations} iterations"
            if not np.all(np.isfinite(x)):
                x = self._least_norm(p.L, p.w, p.factored)
        self._warm_start(self._t_ref)  # not from a diverged iterate
        return TensionResult(p.f0 - x, x, False, reason, iterations)

    def answered_inside(self, t: Array) -> None:
        self._warm_start(t)

    def _warm_start(self, t: Array) -> None:
        """Start the next OSQP run from tensions t (duals zero).  Passed on only when
        OSQP runs: most cycles take the interior shortcut, and the call costs more than
        the copy."""
        self._start = t.copy()

    def _apply_warm_start(self) -> None:
        if self._start is None:
            return
        if self._solver is not None:
            self._solver.warm_start(self._start, self._y0)
        else:
            self._prob.warm_start(x=self._start, y=self._y0)
        self._start = None

    def _run(self, eps: float | None = None) -> tuple[Array, int, int, int]:
        """Push (A, l, u) and solve; with eps, re-solve the same data at that tolerance.

        Returns (x, status, polish status, iterations).
        """
        s = self._solver
        self._apply_warm_start()
        if eps is not None:
            self._set_eps(eps, eps)
        try:
            if s is not None:
                if eps is None and (
                    s.update_data_vec(None, self._l, self._u)
                    or s.update_data_mat(None, None, self._Ax_flat, None)
                ):  # nonzero: osqp kept its old data (it prints why); never solve that
                    self._info = None
                    return self._nan.copy(), _UPDATE_REJECTED, 0, 0
                s.solve()
                info = s.info
                self._last = s.solution
                x = self._last.x  # a fresh copy on every access
            else:
                prob = self._prob
                if eps is None:
                    prob.update(l=self._l, u=self._u, Ax=self._Ax_flat)
                self._last = prob.solve(raise_error=False)
                info, x = self._last.info, self._last.x
            self._info = info
        finally:
            if eps is not None:
                self._set_eps(*self._eps)
        return x, info.status_val, info.status_polish, info.iter  # plain ints

    def _set_eps(self, eps_abs: float, eps_rel: float) -> None:
        if self._solver is not None:
            settings = self._prob.settings
            settings.eps_abs = eps_abs
            settings.eps_rel = eps_rel
            self._solver.update_settings(settings)
        else:
            self._prob.update_settings(eps_abs=eps_abs, eps_rel=eps_rel)

    def _infeasibility_reason(self, p: _Problem) -> str:
        """Name the cable limits in OSQP's primal infeasibility certificate."""
        cert = self._last.prim_inf_cert
        head = "solver status: primal infeasible"
        y = np.asarray(cert, dtype=float)[6:]
        if y.shape != (self.n,) or not np.all(np.isfinite(y)) or not np.any(y):
            return head
        big = float(np.abs(y).max())
        parts = []
        for k, yk in enumerate(y.tolist()):
            if yk > _CERT_RTOL * big:  # upper bound t_hi: |f + f_b| <= force_max
                parts.append(f"cable {k} t <= {p.hi[k]:.4g} N (force_max)")
            elif yk < -_CERT_RTOL * big:
                which = "t_min" if self._t_min[k] >= p.lo[k] else "force_max"
                parts.append(f"cable {k} t >= {p.lo[k]:.4g} N ({which})")
        return f"{head}; the wrench conflicts with the limits: " + ", ".join(parts)


# -- closed form -----------------------------------------------------------------------


class ClosedFormTensionSolver(_TensionSolverBase):
    """F by Pott's improved closed-form method (A. Pott, Computational Kinematics 2014).

    Start from the least-norm solution around t_ref, t = t_ref + Λ (ΛᵀΛ)⁻¹ (w − Λᵀ t_ref);
    while a cable is outside [t_lo, t_hi], fix the one with the largest violation at that
    bound, move its contribution to the right-hand side and re-solve with the others.
    Infeasible when fewer than 6 free cables would remain or the reduced Λ is rank
    deficient.  Not optimal when bounds are active (OSQP is), but at most n − 5 small
    solves: each is a 6 × 6 Cholesky (LAPACK dposv) on rows of Λ with fixed cables zeroed.

    The greedy fixing can miss a feasible wrench (a cable fixed at a bound for good that
    an optimum would leave free: against an independent LP, 1 in 193 random wrenches at
    a 100 N tension reference, 36 at 25 N): before it calls a wrench infeasible, and the
    robot brakes for it, the exact method (OSQP, set up once beside it) decides.
    """

    method = "closed_form"

    def __init__(self, limits: TensionLimits, rtol: float = DEFAULT_RTOL) -> None:
        super().__init__(limits, rtol)
        self._exact = OsqpTensionSolver(limits, rtol=rtol)

    def _solve(
        self,
        jacobian: ArrayLike | FactoredJacobian,
        wrench: ArrayLike,
        f_b: ArrayLike,
        f0: ArrayLike,
        low: _Low,
    ) -> TensionResult:
        p = self._prepare(jacobian, wrench, f_b, f0, low)
        if type(p) is TensionResult:
            return p  # non-finite input: no method can do better
        assert isinstance(p, _Problem)
        result = self._pott(p)
        if result.feasible:
            return result
        exact = self._exact._solve(jacobian, wrench, f_b, f0, low)
        if exact.feasible:
            return exact
        return exact._replace(reason=f"{exact.reason} (closed form: {result.reason})")

    def _pott(self, p: _Problem) -> TensionResult:
        """Pott's method on the prepared problem."""
        L, lo, hi, tol = p.L, p.lo, p.hi, p.tol
        Lf = L  # rows of fixed cables zeroed (copied on the first fix)
        base = self._t_ref  # t_ref for free cables, the bound for fixed ones
        fixed: list[tuple[int, float]] = []  # (cable, its tension when it was fixed)
        t = None
        while True:
            chol, x, info = dposv(Lf.T.dot(Lf), p.w - base.dot(L), overwrite_a=1, overwrite_b=1)
            pivots = chol.diagonal().tolist()
            if info != 0 or min(pivots) < _RANK_RTOL * max(pivots):
                return self._rank_deficient(p, t, fixed)
            t = base + Lf.dot(x)
            viol = np.maximum(lo - t, t - hi)
            k = int(viol.argmax())
            if not viol[k] > tol:
                break
            if self.n - len(fixed) == 6:
                reason = (
                    f"{self._describe(k, p, float(t[k]))}; no redundancy left: fixing it "
                    f"would leave 5 free cables, 6 needed"
                )
                return TensionResult(p.f0 - t, t, False, reason, 0)
            if Lf is L:
                Lf = L.copy()
                base = base.copy()
            Lf[k] = 0.0
            base[k] = lo[k] if lo[k] > t[k] else hi[k]
            fixed.append((k, float(t[k])))
        return self._result(p, t, self._check(p, t), 0)

    def _rank_deficient(
        self, p: _Problem, t: Array | None, fixed: list[tuple[int, float]]
    ) -> TensionResult:
        """Infeasible: the (reduced) Jacobian cannot carry the wrench."""
        if t is None:
            reason = "Jacobian is rank deficient (singular pose)"
            t = self._least_norm(p.L, p.w, p.factored)
        else:
            k, t_k = fixed[-1]
            reason = (
                f"{self._describe(k, p, t_k)}; fixing it at its limit leaves the Jacobian of "
                f"the {self.n - len(fixed)} free cables rank deficient (fixed cables: "
                + ", ".join(str(j) for j, _ in fixed)
                + ")"
            )
        return TensionResult(p.f0 - t, t, False, reason, 0)
