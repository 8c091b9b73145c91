"""Trusted cable lengths: which measured lengths the daemon may believe (DESIGN §9).

The brake and the idle keepalive hold every cable at a length; that length must be one
the robot really has, never a raw frame's value: a forged feedback frame or a glitching
encoder would otherwise make the brake drive the robot.  `TrustedLengths` keeps, per
cable, the last measurement that passed the checks below, and names the drive whose
feedback failed one.  Per cable, against its own last trusted sample taken `elapsed`
seconds before (cycle instants; `slack`: how much later a sample may really have been
taken or seen than its instant says):

- rate: the reported rate is at most `max_speed` (the fastest the drive can wind);
- step: the length moved at most max_speed x (elapsed + slack) + tolerance;
- own rate: the length moved as its rates say, mean rate x elapsed, within tolerance +
  mean rate x slack + max_accel x elapsed^2 / 4: tight while the cable stands still,
  where a glitch or a forged frame would otherwise pass the step bound unnamed.  The
  last term is what a length whose acceleration stays within max_accel may depart from
  the mean of its end rates over `elapsed` (the most, with both end rates given, is
  (a e^2 - dv^2 / a) / 4): 0.02 mm over a 2 ms cycle at 17 m/s^2, but 9 cm over the
  150 ms a stalled host can leave between two trusted samples, where a figure-eight
  turned a cable round (moved +2.0 mm where the end rates gave -0.7 mm: a false brake).
  Only over a gap in which no set was trusted: a cable refused while the others were
  trusted (a forger's frames) gets none, or its allowance would grow with the forgery.
  `cable_accel_bound` gives max_accel from the trajectory limits.

Two answers to one SYNC (`second_answer`; the CiA 402 host records them): their samples
were taken at most `slack` apart (a late answer to the SYNC before, over relays on a
loaded host), so their lengths differ by at most the step bound over no elapsed time,
max_speed x slack + tolerance.  More means another node sends that drive's PDOs (a
node-id conflict or a forger), whichever of the two came first: the length farther from
the trusted one is named.  A drive that streams its feedback (Timing.CYCLIC, ODrive) has
no SYNC to answer twice: each frame replaces the last, and the one a cycle takes is judged.

Across cables (consistency): with n > 6 cables the lengths are redundant.  A rigid
motion changes them by Lambda dx, which has no component in the left null space N of
Lambda; one cable off by e leaves N N^T e_k e, largest on that cable when normalised by
|N_k| (Cauchy-Schwarz).  The change since the trusted set whose largest normalised
residual |N_k . N^T d| / |N_k| exceeds the tolerance is inconsistent.  Cables whose rows
N_k are parallel cannot be told apart this way (reference8 pairs them in two groups of
four at home): the message names every cable that disagrees as much.  N is linearised at
a recent measured pose (`follow_pose`, or in a daemon `note_pose` after a cycle's
commands and `catch_up` at the next tick, while the feedback is on its way), again once
the pose moved REFRESH_DISTANCE: its
rows have turned by up to REFRESH_DISTANCE over the `shortest` cable since, and read up
to that share of a rigid change as residual, which the check allows beside the tolerance
(reference8, flying 4 mm a cycle: up to 58 um; 3 % of the change at its shortest cable).
The change is usually one cycle's, so cable stretch barely enters.
After a gap between trusted sets (a stalled host, lost frames) it is not: the linear
check errs with the square of the change (reference8, measured: about d^2 / 1 m for a
largest cable change d, 0.76 mm at 28 mm, 3.0 mm at 57 mm), which braked flights on
`implausible_feedback` after 90 ms gaps.  A change beyond `linear_reach` (LINEAR_REACH
tolerances: a change no cycle of a live loop makes) that fails the linear check gets a
second look
(`_second_look`): forward kinematics fits a pose to the trusted set and one to the new
set, and the residual each fit leaves is compared, exact however far the platform moved;
a failed second look waits RETRY before the next.

Every cycle's values are judged, a cable's stale value too (a frame may have changed it
since the last cycle).  A complete cycle (every cable fresh and finite) that is
consistent is trusted, except the cables that failed a per-cable check (they keep their
last trusted sample); an inconsistent one updates nothing, and neither does a cycle
missing a cable's sample.

There is no history for the first set (nor after `retrust`): it is trusted when forward
kinematics fits one pose to it within the robot's max_residual (the bound the controller
applies every cycle), the cables stretched by `rest_tensions` (at rest) with the stiffness
identified from the same lengths (`stretch`, cdpr.stretch: an EA far off the robot file's
would fail every first set), and every cable
within its rate and step bounds of any earlier trusted sample.  A first set that fails
names the cable with the largest normalised residual and is retried at most every RETRY
seconds (a failing fit can take a millisecond); after `retrust` a failure keeps the
trusted set and its checks.  With six cables there is no redundancy:
only the per-cable checks protect, and any first set that FK solves is trusted.

Pure and synchronous: lists of floats in, verdicts out; no asyncio, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from cdpr import Pose, Robot
from cdpr.compiled_linalg import kernel_array, left_null_space
from cdpr.stretch import ComplianceScale
from cdpr.trajectory.limits import TrajectoryLimits

RETRY = 0.1  # s between attempts to trust a first set after one failed
RETRUST_CYCLES = 50  # cycles a retrust (a reset, a pretension's homing) waits for a judgement
REFRESH_DISTANCE = 0.01  # m (or rad) the pose may move before N is linearised again
# x feedback_tolerance: the largest change of a cable the linear consistency check judges
# alone (module docstring); at 1 mm, a 1 cm change, where it errs by 0.1 mm on reference8
LINEAR_REACH = 10.0
AS_MUCH = 0.9  # cables within this fraction of the largest residual are as suspect
_UNOBSERVABLE = 1e-6  # |N_k|^2 below which a cable's error cannot be told from motion


@dataclass(frozen=True)
class Implausible:
    """One drive's feedback that was not trusted this cycle, and why."""

    cable: int
    node: int
    value: float  # the length (m) or rate (m/s) that failed
    reason: str  # names the value and the bound

    def message(self) -> str:
        return f"drive {self.cable} (node {self.node}): {self.reason}"


def cable_accel_bound(limits: TrajectoryLimits, attachments: ArrayLike, shortest: float) -> float:
    """The most a cable's length accelerates (m/s^2) along a reference within `limits`:
    with l = a_i - p - R b_i, |L''| <= |l''| + |l'|^2 / L, |l''| <= |p''| + (|w'| + |w|^2)
    |b_i| and |l'| <= |p'| + |w| |b_i|, at the attachments' largest radius |b_i| and the
    `shortest` length a cable has (m)."""
    radius = float(np.max(np.linalg.norm(np.asarray(attachments, dtype=float), axis=1)))
    speed = limits.linear_speed + limits.angular_speed * radius
    turning = limits.angular_accel + limits.angular_speed**2
    return limits.linear_accel + turning * radius + speed * speed / shortest


class TrustedLengths:
    """The last trusted length of each cable (`held`, NaN until the first set is
    trusted) and the checks a new measurement must pass to replace it (module docstring)."""

    def __init__(
        self,
        robot: Robot,
        nodes: Sequence[int],
        *,
        max_speed: float,
        tolerance: float,
        slack: float,
        rest_tensions: Sequence[float],
        max_accel: float = 0.0,
        stretch: ComplianceScale | None = None,
        shortest: float = math.inf,
    ) -> None:
        self.robot = robot
        self.n = n = robot.n_cables
        if len(nodes) != n:
            raise ValueError(f"{len(nodes)} node ids for {n} cables")
        self.nodes = list(nodes)
        self.max_speed = max_speed
        self.tolerance = tolerance
        self.slack = slack
        self.max_accel = max_accel
        self.linear_reach = LINEAR_REACH * tolerance  # m of change judged linearly alone
        # of a change, what N linearised up to REFRESH_DISTANCE away may read as residual
        self.motion_share = REFRESH_DISTANCE / shortest
        self.rest_tensions = np.asarray(rest_tensions, dtype=float)
        self.stretch = ComplianceScale(robot) if stretch is None else stretch
        self.held = [math.nan] * n
        self._rates = [0.0] * n  # the rate of each trusted sample
        self._times = [-math.inf] * n  # the cycle instant of each trusted sample
        self._set_at = -math.inf  # the instant of the last set trusted (whole or in part)
        self._first = True  # the next complete set is checked without history
        self._next_attempt = -math.inf
        self.first_judgements = 0  # complete sets judged like the first (a reset waits)
        self._failed: list[Implausible] = []  # the last failed first set, while it stands
        self._basis: list[list[float]] = []  # rows N_k of the left null space of Lambda
        self._inverse_norms = [0.0] * n  # 1 / |N_k| (0: cable not observable)
        self._pose: Pose | None = None  # where N was linearised
        self._due: Pose | None = None  # where it is to be again (note_pose)
        self._next_look = -math.inf  # no second look before (a failed one waits RETRY)
        # N's kernel loaded now, not in the cycle that first linearises (a compile there)
        left_null_space(np.eye(7, 6), np.empty((7, 1)))

    # -- every cycle ------------------------------------------------------------------

    def check(
        self,
        lengths: Sequence[float],
        rates: Sequence[float],
        fresh: Sequence[bool],
        instant: float,
    ) -> list[Implausible]:
        """Judge one cycle's `lengths` (m) and `rates` (m/s), sampled at `instant` (s,
        monotonic) or, where `fresh[k]` is False, earlier: every value is judged, a stale
        one too (a frame may have changed it since the last cycle, and the controller
        would use it), but only a cycle fresh on every cable updates `held`.  Returns
        the drives whose feedback is implausible (empty: none).  Non-finite values are
        neither trusted nor reported here (the NaN trigger is)."""
        if self._first:
            return self._check_first(lengths, rates, fresh, instant)
        held = self.held
        isfinite = math.isfinite
        flagged: list[Implausible] = []
        change = [0.0] * self.n
        complete = True
        for k in range(self.n):
            x, v = lengths[k], rates[k]
            if not (isfinite(x) and isfinite(v)):
                complete = False
                continue
            complete = complete and fresh[k]
            problem = self._per_cable(k, x, v, instant)
            if problem is None:
                change[k] = x - held[k]
            else:
                flagged.append(problem)
        if not complete:
            return flagged
        residuals = self._residuals(change)
        largest = max(residuals, default=0.0)
        allowed = self.tolerance
        if largest > allowed:  # and the linearisation's share of the change
            moved = max(map(abs, change))
            allowed += self.motion_share * moved
            if largest > allowed and self._far(moved, instant):
                looked = self._second_look(change, instant)
                if looked is not None:  # exact: the tolerance alone
                    residuals, largest, allowed = looked, max(looked), self.tolerance
        if largest > allowed:
            worst = residuals.index(largest)
            if all(f.cable != worst for f in flagged):
                flagged.append(self._disagrees(worst, lengths[worst], residuals, allowed))
            return flagged
        if not flagged:  # the usual cycle: the whole set is trusted
            held[:] = lengths
            self._rates[:] = rates
            self._times[:] = [instant] * self.n
            self._set_at = instant
            return flagged
        rejected = {f.cable for f in flagged}
        self._set_at = instant
        for k in range(self.n):
            if k not in rejected:
                held[k] = lengths[k]
                self._rates[k] = rates[k]
                self._times[k] = instant
        return flagged

    def track(
        self,
        lengths: Sequence[float],
        rates: Sequence[float],
        fresh: Sequence[bool],
        instant: float,
    ) -> list[Implausible]:
        """`check` while pretension winds slack cables in (cdpr.pretension): they move
        without the platform, so the lengths fit no one pose and only the rate and step
        checks apply; each fresh cable that passes them is trusted (a brake holds it where
        it is), and the next complete set `check` sees is judged like the first one."""
        flagged = []
        isfinite = math.isfinite
        for k in range(self.n):
            x, v = lengths[k], rates[k]
            if not (fresh[k] and isfinite(x) and isfinite(v)):
                continue
            problem = self._per_cable(k, x, v, instant, own_rate=False)
            if problem is None:
                self.held[k], self._rates[k], self._times[k] = x, v, instant
            else:
                flagged.append(problem)
        self.retrust()
        return flagged

    def follow_pose(self, pose: Pose) -> None:
        """A pose measured from trusted lengths (the controller's forward kinematics):
        the consistency check is linearised there again once it moved REFRESH_DISTANCE."""
        self.note_pose(pose)
        self.catch_up()

    def note_pose(self, pose: Pose) -> None:
        """follow_pose with the linearisation left for catch_up(): a cycle notes its pose
        after its commands and the next tick catches up, so that the ~30 us it takes each
        time the platform moved REFRESH_DISTANCE falls in no cycle."""
        last = self._pose
        if last is not None:
            (x, y, z), (a, b, c) = pose.position_tuple, last.position_tuple
            w0, x0, y0, z0 = pose.quaternion_tuple
            w1, x1, y1, z1 = last.quaternion_tuple
            dot = abs(w0 * w1 + x0 * x1 + y0 * y1 + z0 * z1)
            angle = 2.0 * math.acos(min(1.0, dot))
            moved2 = (x - a) ** 2 + (y - b) ** 2 + (z - c) ** 2
            if moved2 < REFRESH_DISTANCE**2 and angle < REFRESH_DISTANCE:
                return
        self._due = pose

    def catch_up(self) -> None:
        """Linearise at the pose note_pose left, if any."""
        if self._due is not None:
            self._linearise(self._due)

    def shift(self, changes: Sequence[float]) -> None:
        """The lengths' offsets changed by `changes` (m, homing): the trusted lengths
        move with them, and the next complete set is judged like the first one."""
        self.held[:] = [x + d for x, d in zip(self.held, changes, strict=True)]
        self.retrust()

    def retrust(self) -> None:
        """Check the next complete set like the first one (an explicit reset: the
        measurements are trusted again if they fit one pose).  `held` stays meanwhile,
        and stays trusted if that set fails."""
        self._first = True
        self._next_attempt = -math.inf

    @property
    def retrusting(self) -> bool:
        """A `retrust` asked for has not judged a complete set yet."""
        return self._first and all(map(math.isfinite, self.held))

    def cancel_retrust(self) -> None:
        """Drop a `retrust` that has not judged a set yet: the trusted set and its checks
        stand (a reset that was refused must not leave a fresh start pending)."""
        if self.retrusting:
            self._first = False

    # -- the checks -------------------------------------------------------------------

    def _per_cable(
        self, k: int, x: float, v: float, instant: float, own_rate: bool = True
    ) -> Implausible | None:
        """Rate, step and (with `own_rate`) own-rate checks of cable k's sample (x, v)
        at `instant`."""
        speed = self.max_speed
        if abs(v) > speed:
            return Implausible(
                k, self.nodes[k], v, f"rate {v:+.4f} m/s exceeds max_cable_speed {speed:g} m/s"
            )
        trusted = self.held[k]
        elapsed = instant - self._times[k]
        if elapsed == math.inf or x == trusted:  # nothing trusted yet, or the same sample
            return None
        slack, tolerance = self.slack, self.tolerance
        step = x - trusted
        bound = self._step_bound(elapsed)
        if abs(step) > bound:
            return Implausible(
                k,
                self.nodes[k],
                x,
                f"length {x:.4f} m is {step:+.4f} m from its trusted {trusted:.4f} m after "
                f"{elapsed * 1e3:.1f} ms (bound {bound:.4f} m at max_cable_speed {speed:g} m/s)",
            )
        if not own_rate:
            return None
        mean = 0.5 * (v + self._rates[k])
        expected = mean * elapsed
        # the acceleration's allowance over a gap no set was trusted in (a stalled host),
        # never over one this cable alone was refused in (a forger's, however long)
        gap = elapsed if self._times[k] >= self._set_at else 0.0
        allowed = tolerance + abs(mean) * slack + 0.25 * self.max_accel * gap * gap
        if abs(step - expected) > allowed:
            return Implausible(
                k,
                self.nodes[k],
                x,
                f"length {x:.4f} m moved {step * 1e3:+.2f} mm in {elapsed * 1e3:.1f} ms where "
                f"its rate gives {expected * 1e3:+.2f} mm (allowed {allowed * 1e3:.2f} mm)",
            )
        return None

    def _step_bound(self, elapsed: float) -> float:
        """How far (m) a length may move in `elapsed` s between the instants of two
        samples (module docstring: step)."""
        return self.max_speed * (elapsed + self.slack) + self.tolerance

    def second_answer(self, k: int, first: float, second: float) -> Implausible | None:
        """Cable k answered one SYNC twice, with lengths `first` and `second` (m): an
        Implausible if they are further apart than the step bound over no elapsed time
        (module docstring), naming the one farther from the trusted length (the second
        while none is trusted)."""
        bound = self._step_bound(0.0)
        apart = abs(second - first)
        if not apart > bound:
            return None
        trusted = self.held[k]
        x, other = second, first
        if abs(first - trusted) > abs(second - trusted):  # False while trusted is NaN
            x, other = first, second
        return Implausible(
            k,
            self.nodes[k],
            x,
            f"length {x:.4f} m and {other:.4f} m in two answers to one SYNC, {apart:.4f} m "
            f"apart (bound {bound:.4f} m at max_cable_speed {self.max_speed:g} m/s): a second "
            "answer to one SYNC means another node sends this node's PDOs (node-id conflict "
            "or forgery)",
        )

    def _residuals(self, change: Sequence[float]) -> list[float]:
        """|N_k . N^T change| / |N_k| per cable (m): the part of `change` no rigid motion
        explains.  For the residuals of a least-squares fit (already in the null space)
        it is |residual_k| / |N_k|."""
        basis = self._basis
        if not basis or not basis[0]:
            return [0.0] * self.n
        m = len(basis[0])
        y = [0.0] * m
        for row, d in zip(basis, change, strict=True):
            for j in range(m):
                y[j] += row[j] * d
        out = []
        for row, scale in zip(basis, self._inverse_norms, strict=True):
            r = 0.0
            for j in range(m):
                r += row[j] * y[j]
            out.append(abs(r) * scale)
        return out

    def _far(self, moved: float, instant: float) -> bool:
        """A change (its largest cable's, `moved` m) too large for the linear check
        alone, and no second look failed within RETRY."""
        if instant < self._next_look or self._pose is None:
            return False
        return moved > self.linear_reach

    def _second_look(self, change: Sequence[float], instant: float) -> list[float] | None:
        """The consistency residuals of a long change, from the least-squares poses of
        the trusted set and of the new one (the trusted lengths plus `change`): what each
        fit leaves unexplained, compared (module docstring).  None where either fit
        fails; a look whose residuals exceed the tolerance holds the next off for RETRY
        (a cable really off would otherwise cost two fits a cycle)."""
        robot = self.robot
        held = np.array(self.held)
        after = held + np.asarray(change)
        before_fit = robot.forward_kinematics(held, self._pose)
        after_fit = robot.forward_kinematics(after, before_fit.pose)
        if not (before_fit.converged and after_fit.converged):
            self._next_look = instant + RETRY
            return None
        left = (after - robot.cable_lengths(after_fit.pose)) - (
            held - robot.cable_lengths(before_fit.pose)
        )
        residuals = self._residuals(left.tolist())
        if max(residuals) > self.tolerance:
            self._next_look = instant + RETRY
        return residuals

    def _disagrees(
        self, k: int, x: float, residuals: list[float], allowed: float, why: str = ""
    ) -> Implausible:
        """Cable k disagrees most with the pose the others give, by more than `allowed`
        (m); names the cables that disagree as much (the geometry cannot tell them apart)."""
        largest = residuals[k]
        alike = [
            f"{j} (node {self.nodes[j]})"
            for j, r in enumerate(residuals)
            if j != k and r >= AS_MUCH * largest
        ]
        reason = (
            f"length {x:.4f} m disagrees by {largest * 1e3:.2f} mm with the pose the other "
            f"cables give (feedback_tolerance {self.tolerance * 1e3:.2f} mm"
        )
        if allowed > self.tolerance:
            reason += f" + {(allowed - self.tolerance) * 1e3:.2f} mm for the linearisation"
        reason += ")" + why
        if alike:
            reason += f"; drives {', '.join(alike)} disagree as much: the geometry cannot tell"
            reason += " them apart"
        return Implausible(k, self.nodes[k], x, reason)

    def _check_first(
        self,
        lengths: Sequence[float],
        rates: Sequence[float],
        fresh: Sequence[bool],
        instant: float,
    ) -> list[Implausible]:
        """Trust a complete set that fits one pose (module docstring)."""
        if instant < self._next_attempt:
            return self._failed
        if not all(fresh) or not all(map(math.isfinite, [*lengths, *rates])):
            return self._failed
        self.first_judgements += 1
        flagged = []
        for k in range(self.n):
            problem = self._per_cable(k, lengths[k], rates[k], instant, own_rate=False)
            if problem is not None:
                flagged.append(problem)
        if not flagged:
            robot, stretch = self.robot, self.stretch
            guess = robot.home if self._pose is None else self._pose
            scale = stretch.scale
            fk = stretch.fit(lengths, lambda pose: self.rest_tensions, guess)
            stretched = stretch.stretched(lengths, self.rest_tensions)
            self._linearise(fk.pose)
            if fk.converged:
                self.held[:] = [float(x) for x in lengths]
                self._rates[:] = [float(v) for v in rates]
                self._times[:] = [instant] * self.n
                self._set_at = instant
                self._first, self._failed = False, []
                return []
            stretch.scale = scale  # a fit to lengths that fit no pose says nothing of EA
            residuals = self._residuals((stretched - robot.cable_lengths(fk.pose)).tolist())
            worst = residuals.index(max(residuals))
            why = f"; the lengths fit no pose ({fk.reason})"
            flagged.append(
                self._disagrees(worst, float(lengths[worst]), residuals, self.tolerance, why)
            )
            self._pose = None  # the next attempt starts from home, not from a failed fit
        self._failed = flagged
        self._next_attempt = instant + RETRY
        # a retrust gets one attempt; then the trusted set is judged against as before
        self._first = not all(map(math.isfinite, self.held))
        return flagged

    def _linearise(self, pose: Pose) -> None:
        """N at `pose`: an orthonormal basis of the left null space of Lambda (none with
        no more cables than degrees of freedom); a pose noted before it is superseded."""
        self._due = None
        Lam = self.robot.jacobian(pose)
        cables, freedoms = Lam.shape
        basis = np.zeros((cables, max(cables - freedoms, 0)))
        if cables > freedoms:
            left_null_space(kernel_array(Lam, Lam.shape), basis)
        norms2 = (basis * basis).sum(axis=1)
        self._basis = basis.tolist()
        self._inverse_norms = [
            1.0 / math.sqrt(s) if s > _UNOBSERVABLE else 0.0 for s in norms2.tolist()
        ]
        self._pose = pose
