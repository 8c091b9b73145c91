"""Pretension: from slack cables to the planned tensions without moving the platform
(DESIGN §15 step 4).  Pure: lengths and rates in, forces out.

The platform rests on a docking fixture at a known pose; its cables are slack or at an
unknown tension.  Cycle by cycle (`Pretension.step`):

1. wind: every cable is wound in by a speed servo (wind_speed, PI on the rate, back-EMF
   feed-forward) whose force is clipped at wind_force: a slack cable winds in at
   wind_speed pulling little; once taut it stops, and the servo's integrator winds up to
   the clip, so it pulls wind_force and no more.  A cable is taut when it has pulled
   wind_force while staying within taut_band of one length for taut_time.  A cable not
   taut after taut_timeout, or wound in by more than max_wind_in, aborts (broken or
   unhooked); so does any cable moving faster than twice wind_speed, or paying out
   faster than wind_speed (it carries a load: the platform is not on the fixture).
2. ramp: when every cable is taut at once, all tensions go linearly from wind_force to
   the planned ones (`ramp_target`: the tension distribution for `carry` of the static
   wrench holding the platform at the pose), the largest change at ramp_rate.  The
   cables carry ever more of the weight and the fixture ever less; the platform must
   not move.  The watch: the change of the lengths
   since the ramp began, less the stretch the tension change explains (the robot's
   compliance), mapped to a pose change by least squares (Lambda+); more than
   max_motion (or max_rotation) aborts, naming how far it moved.
3. settle: the planned tensions are held for settle_time, still watched; the mean
   lengths over it are the platform's at the pose under those tensions (homing's input).
4. close (`close`, then `unload` every cycle): the position loop holds the pose with its
   integral action preset to the part of the static wrench the fixture still carries
   (ParallelController.preload): the controller's first command is the distribution of
   the wrench the cables carry, which is the ramp's last (bumpless).  Over unload_time
   the preload is given up (ParallelController.release) and the loop takes the whole
   weight: the platform floats at the pose, a model error in the weight corrected by
   the integral action as in any hold, not by a step.

Why not ramp to the whole weight (carry 1)?  Open loop, the last part of the ramp lifts
a platform lighter than the file says, or pushes one whose anchors are off sideways off
a fixture that no longer presses on it; a loaded fixture locates it until the loop
holds it.  Every force command stays within each drive's force_max (an abort otherwise).
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from cdpr.controller import ParallelController
from cdpr.description import PositiveFloat, StrictModel
from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.tension import TensionSolver

Array = NDArray[np.float64]
SPEED_BANDWIDTH = 30.0  # rad/s of the wind-in speed servo, per unit drum mass m0
INTEGRAL_RATIO = 20.0  # 1/s: the servo's integral gain over its proportional gain
STRETCH_PRIOR = 1e-4  # m: the weight of "the file's EA is right" in the motion watch


class PretensionSpec(StrictModel):
    """`pretension:` how slack cables are wound in and tensioned (cdpr.pretension).
    Forces in N, speeds in m/s, times in s, lengths in m, angles in rad.  wind_force must
    exceed the drums' friction (a drum that cannot turn looks taut)."""

    wind_force: PositiveFloat = 15.0  # N: the most the wind-in pulls; a taut cable pulls this
    wind_speed: PositiveFloat = 0.05  # m/s at which a slack cable is wound in
    taut_band: PositiveFloat = 5e-4  # m: a cable pulling wind_force within it for taut_time is taut
    taut_time: PositiveFloat = 0.2  # s a pulling cable must stay within taut_band to be taut
    taut_timeout: PositiveFloat = 20.0  # s: a cable not taut by then aborts the pretension
    max_wind_in: PositiveFloat = 0.5  # m: winding a cable in further before it is taut aborts
    ramp_rate: PositiveFloat = 200.0  # N/s: how fast the largest tension change of the ramp goes
    settle_time: PositiveFloat = 0.3  # s the planned tensions are held and the lengths averaged
    max_motion: PositiveFloat = 2e-3  # m: a platform displacement beyond it aborts (ramp, settle)
    max_rotation: PositiveFloat = 5e-3  # rad: a platform rotation beyond it aborts (ramp, settle)
    carry: Annotated[float, Field(gt=0.0, le=1.0)] = 0.8
    """The share of the static wrench holding the platform (its weight) that the ramp puts
    on the cables; the position loop takes over the rest in unload_time."""
    unload_time: PositiveFloat = 1.0  # s over which the position loop takes the rest of the weight


def ramp_target(robot: Robot, solver: TensionSolver, pose: Pose, carry: float) -> Array:
    """The tensions the ramp ends at: the distribution of `carry` times the static
    wrench holding the platform at rest at `pose` (ValueError if there is none)."""
    zero = np.zeros(robot.n_cables)
    wrench = carry * robot.bias_wrench(pose, np.zeros(6))
    result = solver.solve(robot.jacobian(pose), wrench, zero, zero)
    if not result.feasible:
        raise ValueError(f"no tension distribution carries {carry:g} of the weight at the pose")
    return result.tensions


class Pretension:
    """One pretension at `pose` (the fixture's) towards `planned` tensions (N), the
    cables' compliance scaled by `compliance_scale` (cdpr.stretch), the cables at
    `lengths` (m) when it begins (`start`: the time of the first step).  `step` every
    cycle; `phase` is wind, ramp, settle, done (then `close`), unload, closed, or aborted
    (`fault` says why, naming the cable)."""

    def __init__(
        self,
        robot: Robot,
        spec: PretensionSpec,
        pose: Pose,
        planned: ArrayLike,
        compliance_scale: float,
        lengths: ArrayLike,
    ) -> None:
        self.robot, self.spec, self.pose = robot, spec, pose
        self.n = n = robot.n_cables
        self.planned = np.asarray(planned, dtype=float)
        over = np.flatnonzero(self.planned > robot.force_max)
        if over.size:
            k = int(over[0])
            raise ValueError(
                f"cable {k}: planned tension {self.planned[k]:.1f} N exceeds its force_max "
                f"{robot.force_max[k]:g} N"
            )
        self.phase = "wind"
        self.fault: str | None = None
        self.start = math.nan  # the time of the first step
        self.forces = np.full(n, -spec.wind_force)  # the last command
        self.taut_at = [math.nan] * n  # s after start each cable first became taut
        self.lengths_at_start = np.asarray(lengths, dtype=float).copy()
        self.motion = 0.0  # m, the largest platform displacement seen while watched
        self.rotation = 0.0  # rad
        self.settled_lengths: Array | None = None  # mean over settle (phase done)
        self._kp = SPEED_BANDWIDTH * robot.m0
        self._ki = INTEGRAL_RATIO * self._kp
        # the winches' drag at the winding speed (back-EMF and friction), fed forward
        self._feed = robot.drag(np.full(robot.n_cables, spec.wind_speed))
        self._integral = np.zeros(n)  # N, the servo's pull beyond its feed-forward
        self._band = self.lengths_at_start.copy()  # each cable's length when it last moved
        self._since = np.zeros(n)  # when each cable last left its band
        self._last_t = math.nan
        lengths_at_pose = robot.cable_lengths(pose)
        self._jacobian = robot.jacobian(pose)
        self._drum_at = lambda t: robot.drum_lengths(lengths_at_pose, t * compliance_scale)
        self._stretch_from = np.zeros(n)  # the drum lengths the model gives at the ramp start
        self._ramp_from = np.full(n, spec.wind_force)
        self._ramp_start = math.nan
        self._ramp_duration = 0.0
        self._baseline = np.zeros(n)
        self._settle_start = math.nan
        self._settle_sum = np.zeros(n)
        self._settle_count = 0
        self._preload = np.zeros(6)  # the wrench the fixture carries when the loop closes
        self._closed_at = math.nan

    @property
    def active(self) -> bool:
        """The forces are this object's (wind, ramp, settle)."""
        return self.phase in ("wind", "ramp", "settle")

    def close(self, controller: ParallelController, pose: Pose, t: float) -> None:
        """Phase done: the position loop holds `pose` (measured after homing) from time t,
        its integral action preset to what the fixture carries (module docstring)."""
        controller.reset(pose)
        model = controller.robot
        self._preload = (self.spec.carry - 1.0) * model.bias_wrench(pose, np.zeros(6))
        controller.preload(self._preload)
        controller.observe_external(False)  # until the fixture's share is given up
        self._closed_at = self._last_t = t
        self.phase = "unload"

    def unload(self, controller: ParallelController, t: float) -> None:
        """Give up the preload by the part of unload_time since the last call (phase
        unload, each cycle before the controller's step); then phase closed."""
        if self.phase != "unload":
            return
        spec = self.spec
        share = min(t, self._closed_at + spec.unload_time) - self._last_t
        self._last_t = t
        if share > 0.0:
            controller.release(-self._preload * (share / spec.unload_time))
        if t >= self._closed_at + spec.unload_time:
            controller.observe_external(True)
            self.phase = "closed"

    def step(self, t: float, lengths: ArrayLike, rates: ArrayLike) -> Array:
        """The force commands (N along +l) for the cycle at time `t` given the measured
        `lengths` (m) and `rates` (m/s); after an abort or the end, the last ones."""
        if not self.active:
            return self.forces
        lengths = np.asarray(lengths, dtype=float)
        rates = np.asarray(rates, dtype=float)
        if math.isnan(self.start):
            self.start = self._last_t = t
            self._since[:] = t
        h = max(t - self._last_t, 0.0)
        self._last_t = t
        spec = self.spec
        paying = np.flatnonzero(rates > spec.wind_speed) if self.phase == "wind" else ()
        if len(paying):
            k = int(paying[0])
            return self._abort(
                f"cable {k} pays out at {rates[k]:+.3f} m/s against the wind-in: it carries a "
                "load (is the platform resting on the fixture?)"
            )
        fast = np.flatnonzero(np.abs(rates) > 2.0 * spec.wind_speed)
        if fast.size:
            k = int(fast[0])
            return self._abort(
                f"cable {k} moves at {rates[k]:+.3f} m/s (bound 2 x wind_speed "
                f"{2.0 * spec.wind_speed:g} m/s)"
            )
        if self.phase == "wind":
            forces = self._wind(t, h, lengths, rates)
        else:
            forces = self._tension(t, lengths)
        if self.active:
            over = np.flatnonzero(np.abs(forces) > self.robot.force_max)
            if over.size:
                k = int(over[0])
                return self._abort(
                    f"cable {k}: force {forces[k]:.1f} N beyond its force_max "
                    f"{self.robot.force_max[k]:g} N"
                )
            self.forces = forces
        return self.forces

    # -- the phases ---------------------------------------------------------------------

    def _wind(self, t: float, h: float, lengths: Array, rates: Array) -> Array:
        spec = self.spec
        pull = spec.wind_force
        error = rates + spec.wind_speed  # > 0: winding in slower than wind_speed
        self._integral = np.clip(self._integral + self._ki * error * h, -pull, pull)
        forces = np.clip(-(self._feed + self._kp * error + self._integral), -pull, pull)
        moved = np.abs(lengths - self._band) > spec.taut_band
        self._band[moved] = lengths[moved]
        self._since[moved] = t
        pulling = forces <= -pull * (1.0 - 1e-9)
        taut = pulling & (t - self._since >= spec.taut_time)
        elapsed = t - self.start
        for k in np.flatnonzero(taut):
            if math.isnan(self.taut_at[k]):
                self.taut_at[k] = elapsed
        wound = self.lengths_at_start - lengths
        deep = np.flatnonzero(wound > spec.max_wind_in)
        if deep.size:
            k = int(deep[0])
            return self._abort(
                f"cable {k} wound in {wound[k]:.3f} m without becoming taut (max_wind_in "
                f"{spec.max_wind_in:g} m): broken or unhooked?"
            )
        if taut.all():
            self._begin_ramp(t, lengths)
            return self._tension(t, lengths)
        if elapsed > spec.taut_timeout:
            slack = ", ".join(str(k) for k in np.flatnonzero(~taut))
            return self._abort(
                f"cable(s) {slack} not taut after {elapsed:.1f} s (taut_timeout "
                f"{spec.taut_timeout:g} s) pulling {pull:g} N: broken, unhooked or stuck?"
            )
        return forces

    def _begin_ramp(self, t: float, lengths: Array) -> None:
        self.phase = "ramp"
        self._ramp_start = t
        change = float(np.abs(self.planned - self._ramp_from).max())
        self._ramp_duration = change / self.spec.ramp_rate
        self._baseline = lengths.copy()
        self._stretch_from = self._drum_at(self._ramp_from)

    def _tension(self, t: float, lengths: Array) -> Array:
        """Ramp and settle: the tensions at time t, after the motion watch."""
        duration = self._ramp_duration
        s = 1.0 if duration <= 0.0 else min(1.0, (t - self._ramp_start) / duration)
        tensions = self._ramp_from + s * (self.planned - self._ramp_from)
        moved = self._watch(lengths, tensions)
        if moved is not None:
            return self._abort(f"{moved} during the tension {self.phase} ({s * 100:.0f} %)")
        if self.phase == "ramp" and s >= 1.0:
            self.phase = "settle"
            self._settle_start = t
        if self.phase == "settle":
            self._settle_sum += lengths
            self._settle_count += 1
            if t - self._settle_start >= self.spec.settle_time:
                self.settled_lengths = self._settle_sum / self._settle_count
                self.phase = "done"
        return -tensions

    def _watch(self, lengths: Array, tensions: Array) -> str | None:
        """How far the platform moved if beyond max_motion / max_rotation, else None.
        The lengths' change since the ramp began is a pose change (Lambda delta) plus the
        stretch the tension change gives, known up to the cables' true stiffness: the
        model's stretch pattern times a factor k, fitted with delta by least squares (n > 6
        cables; k kept near 1 by a prior worth STRETCH_PRIOR of length while the stretch
        is small), so that an EA off the file's does not look like motion."""
        change = lengths - self._baseline
        stretch = self._drum_at(tensions) - self._stretch_from
        n = self.n
        system = np.zeros((n + 1, 7))
        system[:n, :6] = self._jacobian
        system[:n, 6] = stretch
        system[n, 6] = STRETCH_PRIOR
        target = np.append(change, STRETCH_PRIOR)
        delta = np.linalg.lstsq(system, target, rcond=None)[0]
        motion = float(np.linalg.norm(delta[:3]))
        rotation = float(np.linalg.norm(delta[3:6]))
        self.motion = max(self.motion, motion)
        self.rotation = max(self.rotation, rotation)
        spec = self.spec
        if motion > spec.max_motion:
            return (
                f"the platform moved {motion * 1e3:.2f} mm (max_motion "
                f"{spec.max_motion * 1e3:g} mm)"
            )
        if rotation > spec.max_rotation:
            return (
                f"the platform turned {math.degrees(rotation):.3f} deg (max_rotation "
                f"{math.degrees(spec.max_rotation):.3f} deg)"
            )
        return None

    def _abort(self, why: str) -> Array:
        self.phase = "aborted"
        self.fault = why
        return self.forces

    def summary(self) -> dict[str, object]:
        """Phase, per-cable time to taut (s from the start), motion (mm), rotation (deg)."""
        return {
            "phase": self.phase,
            "taut_s": [None if math.isnan(x) else round(x, 4) for x in self.taut_at],
            "motion_mm": self.motion * 1e3,
            "rotation_deg": math.degrees(self.rotation),
            "fault": self.fault,
        }
