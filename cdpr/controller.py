"""The parallel-actuator controller: the paper's §5 steps 1-11 (DESIGN §4).

One object per robot.  Each cycle: sample the reference, forward kinematics from the
measured lengths, the twist from the measured rates, the pose error
theta_d = liediff(eta_r, eta) (the erratum of DESIGN §3: actual minus requested), the
single-actuator controller on each of the 6 tangent components, the command wrench
tau_c = M alpha_c + mu, the back-EMF part f_b = k0 Lambda(eta_r) phi_r (and the robot
file's Coulomb friction along those cable rates, cdpr.friction), the no-load
forces f0 = m0 (Lambda alpha_c + c), the tension distribution f_p = F(tau_c, f_b, f0)
(not in W: infeasible, the daemon brakes), and the commands f_c = f_p + f_b.  With elastic
cables the drums also move the cables' stretch as the tensions change: the rate the
reference's own tensions give it (cdpr.stretch_rate) is added to the drums' rates before
the twist is taken from them, and its winch damping to f_b.

Part of a cycle needs no measurement: the reference sample, the forward-kinematics
guess and its linearisation, f_b and, with model_at = "reference", Lambda, c, M, mu and
the factor of Lambda^T Lambda the tension distribution solves with.  `prepare(t)` does
that part ahead (a daemon calls it while the drives' feedback is on its way), so that
`step(t, ...)` is left with what the measurement decides.

A command computed from the measurement at t acts later: it reaches the drive after the
loop's latency, the drive's force follows it with a lag, and it is held for a period.
The reference, the feed-forward and the model are evaluated for the middle of that
interval, t + lead (ControllerSpec.command_lead); the pose error compares the
measurement with the reference at t, its own instant.
"""

from __future__ import annotations

import copy
import math
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.command import command, out_parts, out_size
from cdpr.control_spec import DEFAULT_FORCE_LAG, MAX_COMMAND_LEAD, ControllerSpec
from cdpr.dynamics import PlatformInertia
from cdpr.forward_kinematics import FKResult, fit_result, fit_start, non_finite_lengths
from cdpr.measurement import (
    DIFFERENTIATED,
    ERROR,
    FILTERED_RATES,
    FROM_RATES,
    MEMORY_SIZE,
    OUT_SIZE,
    POSE,
    TWIST,
    measure,
)  # fmt: skip
from cdpr.payload import PayloadEstimate
from cdpr.pose import Pose, retract
from cdpr.robot import Robot, split_model
from cdpr.so3 import quat_to_r9
from cdpr.stretch import ComplianceScale
from cdpr.stretch_rate import TensionRate, stretch_time
from cdpr.tension import (
    FactoredJacobian,
    Shortcut,
    TensionLimits,
    TensionResult,
    TensionSolver,
    make_tension_solver,
)
from cdpr.trajectory import Reference
from cdpr.trajectory.core import evaluate_segment
from cdpr.wrench_observer import WrenchObserver

Array = NDArray[np.float64]
_ZERO6 = np.zeros(6)
_ZERO6_LIST = [0.0] * 6
_NO_RATE = np.empty(0)  # measure's stretch rate where the drums move with the cables


class ReferenceSource(Protocol):
    """Anything that gives the requested (eta_r, phi_r, alpha_r) at time t (a Trajectory)."""

    def sample(self, t: float) -> Reference: ...


class Hold:
    """A reference that stays at one pose, at rest."""

    def __init__(self, pose: Pose) -> None:
        self.reference = Reference(pose, _ZERO6.copy(), _ZERO6.copy())

    def sample(self, t: float) -> Reference:
        return self.reference


class Switch:
    """`before` until time `at`, `after` from then on: a transition planned to begin at
    `at` from `before`'s state there takes over exactly when it begins (following it
    earlier would jump to its start state, held at rest)."""

    def __init__(self, before: ReferenceSource, after: ReferenceSource, at: float) -> None:
        self.before, self.after, self.at = before, after, at

    def sample(self, t: float) -> Reference:
        return self.after.sample(t) if t >= self.at else self.before.sample(t)


def _pending(source: ReferenceSource, t: float) -> ReferenceSource:
    """`source` without the switches made by time t (what came before them is over)."""
    if not isinstance(source, Switch):
        return source
    if source.at <= t:
        return _pending(source.after, t)
    before = _pending(source.before, t)
    return source if before is source.before else Switch(before, source.after, source.at)


def tension_solver(robot: Robot, spec: ControllerSpec) -> TensionSolver:
    """The tension distribution the controller config asks for (method, reference)."""
    limits = TensionLimits.from_robot(robot, spec.tension.reference, spec.tension.floor)
    return make_tension_solver(spec.tension.method, limits)


def static_tensions(robot: Robot, tension: TensionSolver, pose: Pose) -> Array:
    """The planned tensions that hold the platform at rest at `pose` (the reference
    tensions where no distribution exists: the next cycle reports that)."""
    zero = np.zeros(robot.n_cables)
    result = tension.solve(robot.jacobian(pose), robot.bias_wrench(pose, _ZERO6), zero, zero)
    return result.tensions if result.feasible else tension.limits.t_ref.copy()


class ControlOutput(NamedTuple):
    """One cycle's commands and everything that led to them.

    feasible is False when the cycle produced no safe command (forward kinematics
    failed, non-finite values, or the wrench is not in W); `reason` says why, and the
    daemon brakes.  `commands` are NaN unless feasible.
    """

    commands: Array
    feasible: bool
    reason: str
    reference: Reference
    pose: Pose
    twist: Array
    fk_residual: float
    theta_d: Array
    alpha_c: Array
    tau_c: Array
    f0: Array
    f_b: Array
    f_p: Array
    tensions: Array


class _Prepared(NamedTuple):
    """A cycle's measurement-free part (see prepare)."""

    t: float
    reference: Reference  # at t: what the measurement is compared with
    compared: Array  # its pose (p, q) and twist, as cdpr.measurement takes them
    ahead: Reference  # at t + lead: what the command is for
    guess: Pose  # forward kinematics' start
    start: tuple[Array, int, Array, Array, Array]  # the guess (p, q), its linearisation
    accel: Array  # ahead's, as cdpr.command takes it
    f_b: Array  # with the winches' share of the cables' stretching (cdpr.stretch_rate)
    model: tuple[Array, Array, Array, Array] | None  # (Lambda, c, M, mu) at `ahead`
    tables: tuple[Array, Array] | None  # the model as cdpr.command takes it
    factored: FactoredJacobian | None  # model's Lambda for the tension distribution
    stretch_rate: Array | None  # m/s the drums move beyond the cables (None: at rest)


class ParallelController:
    """The paper's controller for `robot` with the settings of `spec` (DESIGN §4-§6),
    for drives whose force follows their commands with a first-order lag `drive_lag`
    (s; what command_lead "auto" allows for)."""

    def __init__(
        self,
        robot: Robot,
        spec: ControllerSpec | None = None,
        drive_lag: float = DEFAULT_FORCE_LAG,
    ) -> None:
        self.spec = spec = spec or ControllerSpec()
        self.period = spec.period
        # the payload estimate (cdpr.payload) moves this controller's own model only
        self.payload: PayloadEstimate | None = None
        if spec.adaptation.enabled:
            robot = copy.copy(robot)
            self.payload = PayloadEstimate(robot, spec.adaptation, self.period, drive_lag)
        self.robot = robot
        # the external wrench the model does not explain (cdpr.wrench_observer)
        self.observer: WrenchObserver | None = None
        if spec.disturbance_observer.enabled:
            o = spec.disturbance_observer
            self.observer = WrenchObserver(
                self.period, o.bandwidth_hz, o.force_max, o.torque_max,
                max_delay=MAX_COMMAND_LEAD + self.period, release_hz=o.release,
            )  # fmt: skip
        self.drive_lag = drive_lag
        self.lead = spec.lead(drive_lag)  # s: see set_latency
        self.loop = spec.linear_controller().discretise(self.period, 6, spec.discretisation)
        self.tension = tension_solver(robot, spec)
        # the reference's own tensions (cdpr.stretch_rate), solved apart: a solver that
        # warm-starts from its last problem keeps the commands' to itself
        self._reference_tension = tension_solver(robot, spec)
        at_home = robot.cable_lengths(robot.home)
        lag = stretch_time(robot.m0, at_home, robot.compliance, drive_lag)
        self._tension_rate = TensionRate(lag)
        self._at_reference = spec.model_at == "reference"
        self._smoothing = self.period / (spec.velocity_filter + self.period)
        self._stretch_corrected = bool(np.any(robot.compliance > 0.0))
        self._compliance = np.array(robot.compliance, dtype=float)  # the kernel's own copy
        if spec.velocity == "differentiate":
            self._twist_from = DIFFERENTIATED
        else:
            self._twist_from = FILTERED_RATES if self._stretch_corrected else FROM_RATES
        self.stretch = ComplianceScale(robot)  # the cables' EA as identified (cdpr.stretch)
        self._observer_held = False  # hold_observer(): kept by reset()
        self._m0 = np.array(robot.m0, dtype=float)  # the kernels' own copies
        self._no_wrench = np.zeros(6)
        self._shortcut = self.tension.shortcut()  # None: the solver takes none
        zero = np.zeros(robot.n_cables)
        self._no_shortcut = Shortcut(zero, zero, zero, 1.0, 1.0)  # cdpr.command's types
        # numba loads the trajectories' kernel at its first call: here, not in a cycle
        evaluate_segment(np.zeros((6, 18)), (1.0, 0.0, 0.0, 0.0), 0.0)
        self._load_kernels()
        self.reset(robot.home)

    def _load_kernels(self) -> None:
        """Run the cycle's kernels once, at home at rest: numba loads each at its first
        call, here, not in a control cycle (reset() then clears what they moved)."""
        robot = self.robot
        self.reset(robot.home)
        prepared = self._prepare(0.0)
        drums = robot.drum_lengths(self._drums, self._tensions)  # unstretched under them
        _, measured = self._measure(drums, np.zeros(robot.n_cables), self.period, prepared)
        assert measured is not None, "the controller's own home does not measure"
        tables = robot.model_tables(robot.home, _ZERO6)
        self._command(prepared, measured, tables, self._no_wrench, split_model(*tables))

    def reset(self, pose: Pose) -> None:
        """Hold `pose`, zero the controller state, restart forward kinematics from it
        (on enable, after a brake: the platform is at rest)."""
        self.source: ReferenceSource = Hold(pose)
        self.loop.reset()
        if self.payload is not None:
            self.payload.clear()
        if self.observer is not None:
            self.observer.clear()
        self._observed: tuple[Array, Array, Array, float] | None = None  # for the observer
        self._observing = True  # the external wrench observer takes in cycles
        self._pose = pose
        self._twist = _ZERO6.copy()
        self._tensions = static_tensions(self.robot, self.tension, pose)
        self._drums = self.robot.cable_lengths(pose)  # the last measured drum lengths
        self._tension_rate.clear()
        # what a cycle's measurement leaves the next (cdpr.measurement): at rest here
        self._memory = np.zeros(MEMORY_SIZE)
        self._memory[POSE] = (*pose.position_tuple, *pose.quaternion_tuple)
        self._prepared: _Prepared | None = None
        self._last_t = -math.inf  # the time of the last step
        # the last reference terms, with the Reference and the platform model they are for
        self._terms: tuple[Reference, PlatformInertia, tuple] | None = None

    def follow(self, source: ReferenceSource, at: float | None = None) -> None:
        """Track `source` (a validated trajectory) from the next cycle, or from time `at`
        (the current source until then; `source` must begin there from its state)."""
        if at is not None:
            source = Switch(_pending(self.source, self._last_t), source, at)
        self.source = source
        self._prepared = None  # sampled from the old source

    def set_latency(self, latency: float) -> None:
        """The measured time (s) from a measurement's instant to its command leaving for
        the drives: with command_lead "auto", the lead allows for it from the next cycle
        (a daemon feeds it, filtered; lock-step runs apply commands at once)."""
        if not 0.0 <= latency < math.inf:
            raise ValueError(f"latency must be finite and >= 0 s, got {latency!r}")
        self.lead = self.spec.lead(self.drive_lag, latency)
        if self.payload is not None:
            self.payload.set_latency(latency)
        self._prepared = None  # evaluated for the old lead

    def prepare(self, t: float) -> None:
        """Compute the measurement-free part of the step at time t ahead of it: the
        reference samples (at t, and at t + lead for the command), the forward-kinematics
        guess and its linearisation, f_b and, with model_at = "reference", the model terms
        and the tension distribution's factor of Lambda; and the last
        cycle's step of the cables' stiffness estimate (cdpr.stretch), of the payload
        estimate (cdpr.payload, whose model the terms then use) and of the external
        wrench observer (cdpr.wrench_observer, whose estimate the command cancels).
        step(t, ...) uses it; a step at another time, reset(), follow() and
        set_latency() discard it."""
        if self.payload is not None and self.payload.update():
            self._take_over(self.payload.platform)
        if self._observed is not None:
            assert self.observer is not None
            twist, M, net, interval = self._observed
            self.observer.update(twist, M, net, self.lead, type(self.source) is Hold, interval)
            self._observed = None
        self._prepared = self._prepare(t)
        self.stretch.update(self.period)

    def _prepare(self, t: float) -> _Prepared:
        """prepare's part that its estimators' steps do not change (at time t)."""
        robot = self.robot
        ref = self.source.sample(t)
        ahead = self.source.sample(t + self.lead) if self.lead else ref
        guess = retract(self._pose, self._twist * self._interval(t))
        start = (np.array((*guess.position_tuple, *guess.quaternion_tuple)),
                 *fit_start(robot.linearise_at(guess)))  # fmt: skip
        compared = np.array((*ref.pose.position_tuple, *ref.pose.quaternion_tuple, *ref.twist))
        # a reference at rest (a Hold, a trajectory after its end) is one Reference
        # sample after sample: its terms stand while the platform model does
        terms = self._terms
        if terms is None or terms[0] is not ahead or terms[1] is not robot.platform:
            terms = self._terms = (ahead, robot.platform, self._reference_terms(ahead))
        f_b, model, tables, factored, tensions = terms[2]
        stretch_rate = self._tension_rate.add(t + self.lead, tensions)
        if stretch_rate is not None:  # the drums move the stretch too: the winches' share
            stretch_rate = self._drums * robot.compliance * self.stretch.scale * stretch_rate
            f_b = f_b - robot.k0 * stretch_rate
        accel = np.array(ahead.accel, dtype=float)
        f_b = f_b if f_b.flags.writeable else f_b.copy()  # the kernel's type
        return _Prepared(t, ref, compared, ahead, guess, start, accel, f_b, model, tables,
                         factored, stretch_rate)  # fmt: skip

    def _reference_terms(
        self, ahead: Reference
    ) -> tuple[
        Array,
        tuple[Array, Array, Array, Array] | None,
        tuple[Array, Array] | None,
        FactoredJacobian | None,
        Array | None,
    ]:
        """What the command for reference `ahead` needs of it alone: f_b, with
        model_at = "reference" the model's tables (Robot.model_tables), its terms and the
        tension distribution's factor of their Lambda, and for elastic cables the tensions
        the reference needs (None: not in W).  Read-only arrays but the tables (for the
        command kernel, which only reads them): a reference at rest reuses them every
        cycle."""
        robot = self.robot
        tables = robot.model_tables(ahead.pose, ahead.twist) if self._at_reference else None
        model = split_model(*tables) if tables is not None else None
        Lam_r = model[0] if model is not None else robot.jacobian(ahead.pose)
        f_b = robot.drag(Lam_r.dot(ahead.twist))  # ndarray.dot: see cdpr.kinematics
        factored = self.tension.factored(Lam_r) if model is not None else None
        tensions = None
        if self._stretch_corrected:
            Lam, c, M, mu = model or robot.model_terms(ahead.pose, ahead.twist)
            accel = ahead.accel
            f0 = robot.m0 * (Lam.dot(accel) + c)
            result = self._reference_tension.solve(factored or Lam, M.dot(accel) + mu, f_b, f0)
            tensions = result.tensions if result.feasible else None
        for array in (f_b, *(model or ()), *(factored or ()), tensions):
            if array is not None:
                array.setflags(write=False)
        return f_b, model, tables, factored, tensions

    def set_payload(self, mass: float, center_of_mass: tuple[float, ...]) -> None:
        """Use this platform mass (kg) and centre of mass (m, platform frame) from now on
        (identify-payload's estimate, applied); ValueError naming the limit if it lies
        beyond controller.adaptation's, or the estimate is off."""
        if self.payload is None:
            raise ValueError("the payload estimate is off (controller.adaptation.enabled)")
        self.payload.set(mass, center_of_mass)
        self._take_over(self.payload.platform)
        self._prepared = None  # its model is the old one

    def _take_over(self, platform: PlatformInertia) -> None:
        """Use `platform` in the model from now on; what its static wrench changes the
        integral action gives up at once, as far as it holds it
        (DiscreteController.hand_over): the integral held the payload until the estimate
        knew it, and would hold it twice after."""
        robot = self.robot
        R = quat_to_r9(*self._pose.quaternion_tuple)
        before = robot.platform.mass_and_bias(R, _ZERO6_LIST)[6::7]
        after = platform.mass_and_bias(R, _ZERO6_LIST)[6::7]
        robot.platform = platform
        change = [a - b for a, b in zip(after, before, strict=True)]
        if self.observer is not None and self._observing and not self._observer_held:
            # it held the rest until now
            self.observer.take_over(np.array(change))
        self.loop.hand_over(-np.linalg.solve(robot.mass_matrix(self._pose), change))

    def preload(self, wrench: ArrayLike) -> None:
        """Start the integral action holding `wrench` (force, torque about p) beyond the
        model's static one, at the pose of the last reset: the loop closes where a fixture
        still carries part of the load without a step in force (cdpr.pretension).
        ValueError without integral action."""
        self.loop.preset(np.linalg.solve(self.robot.mass_matrix(self._pose), wrench))

    def observe_external(self, observing: bool) -> None:
        """Let the external wrench observer take in cycles (True, the default after
        reset()) or keep it where it is (False): while a fixture may still carry part of
        the load (cdpr.pretension's unload), the observer would cancel the fixture's
        reaction within a fraction of a second and so keep the load on the fixture."""
        self._observing = observing

    def hold_observer(self, held: bool) -> None:
        """Keep the external wrench observer out of the loop (True) or let it back in
        (False, the default; reset() keeps what was set).  Held, its estimate is neither
        subtracted from the command nor updated, and reads zero: what it held, the
        integral action takes on at once (DiscreteController.take_on: no step in force);
        let back in, it starts from zero (the motion meanwhile is not its to take in).

        Out of the loop rather than frozen, for `cdprd calibrate`: each pose's lengths
        and forces are to be those the robot file's model holds with its integral action
        alone, the geometry error left uncompensated for the fit to see.  Taking in
        cycles, the observer compensates the error as the poses are flown (the anchors
        came out twice as far off); frozen, it would carry the error of the pose where it
        stopped to every other pose, where it is another."""
        observer = self.observer
        if observer is None or held == self._observer_held:
            return
        self._observer_held = held
        if held:
            M = self.robot.mass_matrix(self._pose)
            self.loop.take_on(-np.linalg.solve(M, observer.estimate))
        observer.clear()
        self._observed = None

    @property
    def observer_held(self) -> bool:
        """The external wrench observer is kept out of the loop (hold_observer)."""
        return self._observer_held

    def release(self, wrench: ArrayLike) -> None:
        """Move the wrench the integral action holds by `wrench`, as far as it holds one
        of the opposite sign (DiscreteController.hand_over): a preload given up."""
        self.loop.hand_over(np.linalg.solve(self.robot.mass_matrix(self._pose), wrench))

    @property
    def pose(self) -> Pose:
        """The last measured pose (forward kinematics)."""
        return self._pose

    def step(self, t: float, lengths: ArrayLike, length_rates: ArrayLike) -> ControlOutput:
        """One control cycle at time t (s) from the measured lengths and rates."""
        robot = self.robot
        if self._prepared is None or self._prepared.t != t:
            self.prepare(t)
        prepared = self._prepared
        assert prepared is not None
        self._prepared = None
        interval = self._interval(t)
        self._last_t = t
        if type(self.source) is Switch and self.source.at <= t:
            # what came before the switch is over: let it go (its memory with it)
            self.source = _pending(self.source, t)
        ref = prepared.reference
        if self.payload is not None and self.payload.fault:
            return self._fault(ref, self._pose, 0.0, self.payload.fault)
        if self.observer is not None and self.observer.fault:
            return self._fault(ref, self._pose, 0.0, self.observer.fault)
        # the encoders measure the drums (a copy: the caller may reuse its array); the
        # last planned tensions stretch the cables
        lengths = np.array(lengths, dtype=float)
        rates = np.array(length_rates, dtype=float)
        n = self._drums.shape[0]
        if lengths.shape != (n,) or rates.shape != (n,):
            raise ValueError(f"expected {n} cable lengths and rates, got {lengths.shape} and "
                             f"{rates.shape}")  # fmt: skip
        self._drums, stretched_by = lengths, self._tensions
        fk, measured = self._measure(lengths, rates, interval, prepared)
        if not fk.converged:
            return self._fault(ref, fk.pose, fk.residual, f"forward kinematics: {fk.reason}")
        self.stretch.observe(lengths, stretched_by, fk)
        pose = fk.pose
        if measured is None:
            return self._fault(ref, pose, fk.residual, "non-finite twist from the drives' rates")
        twist = measured[TWIST]
        self._pose, self._twist = pose, twist

        if prepared.model is not None and prepared.tables is not None:  # both, or neither
            model, tables = prepared.model, prepared.tables
        else:  # at the measured state, carried to t + lead
            tables = robot.model_tables(retract(pose, twist * self.lead), twist)
            model = split_model(*tables)
        cancelled = self.observer is not None and not self._observer_held
        # the push the model does not explain, cancelled
        observed = self.observer.estimate if cancelled else self._no_wrench
        result, commands, out = self._command(prepared, measured, tables, observed, model)
        alpha_c, tau_c, f0 = out_parts(out)[:3]
        if cancelled and self._observing:
            M, mu = model[2], model[3]
            self._observed = (twist, M, tau_c - mu, interval)
        f_b = prepared.f_b
        if result.feasible:
            self._tensions = result.tensions
            if self.payload is not None:
                self.payload.observe(
                    t, pose, fk, lengths, stretched_by, self.stretch.scale,
                    rates, commands, ref,
                )  # fmt: skip
        return ControlOutput(
            commands,
            result.feasible,
            "" if result.feasible else f"wrench not in W: {result.reason}",
            ref,
            pose,
            twist,
            fk.residual,
            measured[ERROR],
            alpha_c,
            tau_c,
            f0,
            f_b,
            result.forces,
            result.tensions,
        )

    def _command(
        self,
        prepared: _Prepared,
        measured: Array,
        tables: tuple[Array, Array],
        observed: Array,
        model: tuple[Array, Array, Array, Array],
    ) -> tuple[TensionResult, Array, Array]:
        """Steps 6-10 on the cycle's measurement (cdpr.command): the loop, tau_c less the
        `observed` wrench, f0 and, where the least-norm tensions meet every bound, the
        commands, in one kernel; elsewhere the solver decides from its tau_c and f0.
        Returns the tension result, the commands (NaN unless it is feasible) and the
        kernel's `out` (alpha_c, tau_c, f0, ...)."""
        n = self.robot.n_cables
        out = np.empty(out_size(n))
        K, stack, order = self.loop.kernel_terms()
        table, G = tables
        shortcut = self._shortcut or self._no_shortcut
        inside = command(
            K, stack, order, measured, prepared.accel, table, G, self._m0, observed,
            prepared.f_b, *shortcut, self._shortcut is not None, out,
        )  # fmt: skip
        _, tau_c, f0, forces, tensions, commands = out_parts(out)
        if inside:
            self.tension.answered_inside(tensions)
            return TensionResult(forces, tensions, True, "", 0), commands, out
        jacobian = model[0] if prepared.factored is None else prepared.factored
        f_b = prepared.f_b
        result = self.tension.solve(jacobian, tau_c, f_b, f0)
        commands = result.forces + f_b if result.feasible else np.full(n, np.nan)
        return result, commands, out

    def _interval(self, t: float) -> float:
        """Seconds from the last step to one at `t`: the period, unless a cycle came late
        or was skipped (a host held up: the drives latched their positions that much
        apart, and differences over it are not a period's); the period before the first."""
        elapsed = t - self._last_t
        return elapsed if 0.0 < elapsed < math.inf else self.period

    def _measure(
        self, lengths: Array, rates: Array, interval: float, prepared: _Prepared
    ) -> tuple[FKResult, Array | None]:
        """Forward kinematics of the drums' `lengths` and, where it converged, the
        measurement (cdpr.measurement's `out`: pose, twist, pose error and its rate), or
        None where the twist came out non-finite (NaN or inf in the rates).

        The twist: phi = Lambda^+ l' (least squares, with forward kinematics' Lambda and
        its normal-equations factor) corrected for cable stretch, or filtered differences
        of forward-kinematics poses.  Drums report l', but a stretching cable's length
        also moves with its tension (L' = l' (1 + t/EA) + l t'/EA), a large error for a
        tilting platform whose internal forces swing, or a lift that changes every
        tension.  The part the reference's own tensions explain (l t'/EA,
        cdpr.stretch_rate) is added to the rates; the low-frequency part of what remains
        is taken from the poses (which are stretch-corrected) through a low-pass of time
        constant velocity_filter: a complementary filter, quiet like the drives' rates
        at high frequency and consistent with the poses at low frequency.  The poses'
        difference over a period is the mean twist over it, so it is compared with the
        mean of this and the last cycle's drive twists (against this one alone the
        estimate would lag half a period: a bias of -alpha T/2).  `interval`: seconds
        since the last pose.  The pose error is step 5 with the erratum of DESIGN §3:
        theta_d = liediff(eta_r, eta) ~ eta - eta_r and its rate phi - phi_r (actual
        minus requested)."""
        guess = prepared.guess
        bad = non_finite_lengths(guess, lengths)
        if bad is not None:
            return bad, None
        settings, stretch_rate = self.robot.fk_settings, prepared.stretch_rate
        start, kind, lengths0, J0, L0 = prepared.start
        out = np.empty(OUT_SIZE)
        status, finite, iterations, residual, p, q, J, U, factored = measure(
            self.robot.geometry.rows, lengths, self._compliance, self._tensions,
            self.stretch.scale, kind, start, lengths0, J0, L0, settings.max_iterations,
            settings.step_tolerance**2, settings.max_residual, rates,
            _NO_RATE if stretch_rate is None else stretch_rate, self._twist_from,
            self._smoothing, interval, self._memory, prepared.compared, out,
        )  # fmt: skip
        fk = fit_result(guess, settings, status, iterations, residual, p, q, J, U, factored)
        return fk, out if finite else None

    def _fault(self, ref: Reference, pose: Pose, residual: float, reason: str) -> ControlOutput:
        nan6, nan_n = np.full(6, np.nan), np.full(self.robot.n_cables, np.nan)
        return ControlOutput(
            nan_n, False, reason, ref, pose, nan6, residual, nan6, nan6, nan6,
            nan_n, nan_n, nan_n, nan_n,
        )  # fmt: skip
