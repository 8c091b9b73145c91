"""The commands that plan: hold, goto and trajectories (DESIGN §7, §16).

Validation and transition planning take milliseconds to seconds; the real-time core
must never wait for them.  The planner does that work wherever it runs (the companion
process; in-process tests and tools beside the core on one loop) and hands the core a
validated, planned trajectory together with the version of the reference it was planned
from: the core follows it only if that reference still stands and the start still lies
ahead, else the planner plans again from what the core runs now.

`Planner` implements daemon.service.api.DaemonHandler over a `CoreLink`: `LocalLink`
calls a Service on the same loop, daemon.process.companion_link.RemoteLink reaches the
core process.  Each motion has one owner, the client that asked for it
(daemon.service.motion): another client's request is refused while it runs, unless it
preempts.
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable, Generator
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeVar

from cdpr.controller import tension_solver
from cdpr.path import Path
from cdpr.pose import Pose
from cdpr.pose_limits import PoseLimits
from cdpr.trajectory import (
    LengthLimits,
    Reference,
    Trajectory,
    TrajectoryError,
    Waypoint,
    WrenchCheck,
    approach_steps,
    check_start_delay,
    check_target,
    goto_steps,
    stop_steps,
    validate,
    validation_steps,
)
from daemon.config import DaemonConfig, check_workspace
from daemon.service.api import UNNAMED, Claim, CommandError, rejection
from daemon.service.calibration_state import OffsetStore, robot_identity
from daemon.service.identify_payload import identify_payload
from daemon.service.lease import HELD_BY, Kept, Leases
from daemon.service.motion import MOVING, Motion, Motions

if TYPE_CHECKING:
    from cdpr.workspace_check import WorkspaceCheck

STATUS_REPLIES = ("status", "enable", "disable", "brake", "reset")  # the core replies its status
PLANNING_LEAD = 0.05  # s ahead of now a planned transition begins (planning takes time)
HOLD_LEAD = 0.01  # the same for a hold, which should not wait: from a moving reference
# it plans in ~13 ms (bench/trajectory.py `hold`); one that comes late is planned again
MIN_LEAD = 0.005  # s: the least lead tried again after a plan came too late
SETTLE_ATTEMPTS = 3  # plans of an approach that begins later, from the state it begins at
HOLD_ATTEMPTS = 6  # a hold is never refused for want of time: it tries with longer leads
EventSink = Callable[[dict[str, Any]], None]
Result = TypeVar("Result")


def path_timer(config: DaemonConfig, margin: float | None = None) -> Callable[[Path], Trajectory]:
    """How the daemon times a path's poses into a trajectory (cdpr.path.timing): within
    its robot's tensions kept `margin` N inside their range (default workspace.margin)
    and its trajectory limits.  The zenoh interface times `<prefix>/path` with it, and
    `cdprd plan` shows what it gives."""
    chosen = config.workspace.margin if margin is None else margin

    def timed(path: Path) -> Trajectory:
        # the path timing's modules at the first path timed, in the parse thread, never
        # at the daemon's start
        from cdpr.path.timing import Timing, time_path

        return time_path(path, config.robot, config.trajectory, Timing(margin=chosen))

    return timed


def daemon_wrench_check(config: DaemonConfig) -> WrenchCheck:
    """The wrench check the daemon validates trajectories with: the controller's model
    and its tension distribution (cdpr.wrench_check; imported here, with the workspace
    check: the validation's kernels are the companion's, not the real-time core's)."""
    from cdpr.wrench_check import wrench_check

    return wrench_check(config.robot, tension_solver(config.robot, config.controller))


def load_checks(config: DaemonConfig) -> None:
    """Load the compiled kernels validation runs (numba compiles them on a cold cache:
    seconds to minutes), where nothing waits on this thread yet, by validating a moment
    at rest at home as the daemon validates a client's trajectory; ConfigError if home
    lies outside the workspace (check_workspace).  A process running a control cycle
    calls it (or builds its Planner) before the cycle runs; the companion before the
    core's hang timer does."""
    check_workspace(config)
    home = config.robot.home
    validate_as_the_daemon(Trajectory([Waypoint(0.0, home), Waypoint(0.1, home)]), config)


def validate_as_the_daemon(trajectory: Trajectory, config: DaemonConfig) -> None:
    """Validate `trajectory` as the daemon validates a client's (rates, poses, cable
    lengths, the wrench set, the workspace), for the robot at rest in its configured
    limits (the Planner checks against the live ones, step by step between cycles):
    TrajectoryError names the first problem.  `cdprd plan` shows its verdict."""
    validate(
        trajectory,
        config.robot,
        config.trajectory,
        daemon_wrench_check(config),
        config.reference_limits,
        config.reference_lengths,
        workspace=config.workspace_check,
    )


class CoreLink(Protocol):
    """What the planner needs of the real-time core."""

    def now(self) -> float:
        """The core's controller time (s; CLOCK_MONOTONIC since the core started)."""
        ...

    @property
    def safety_state(self) -> str:
        """The core's safety state (daemon.service.safety.SafetyState value), as last
        known."""
        ...

    def command(self, name: str, args: dict[str, Any]) -> Awaitable[dict[str, Any]]:
        """Run a core command (enable, disable, brake, reset, status): its reply body,
        or CommandError."""
        ...

    def command_keeping(
        self, name: str, args: dict[str, Any], leases: Kept
    ) -> Awaitable[dict[str, Any]]:
        """Run the core command `name` (payload, observer) and, if the core takes it, have
        it keep `leases` for a companion that starts later (daemon.service.lease)."""
        ...

    async def reference_at(self, t: float) -> tuple[Reference, int]:
        """The reference the core will follow at controller time t, and the version of
        the source it comes from."""
        ...

    async def follow(self, trajectory: Trajectory, version: int, what: str) -> dict[str, Any]:
        """Have the core follow `trajectory` (planned from source `version`): the reply
        body, {"replan": "moved" | "late"} if the source changed or the start passed
        meanwhile, or CommandError."""
        ...

    async def run_steps(self, steps: Generator[Any, None, Result]) -> Result:
        """A step generator (validation, planning) run to its result, out of the
        cycle's way."""
        ...

    def state(self) -> dict[str, Any]:
        """The latest state snapshot to publish."""
        ...

    async def slack(self) -> None:
        """Return when publishing the state costs the cycle nothing."""
        ...

    def subscribe(self, sink: EventSink) -> None:
        """Receive every event of the core."""
        ...


class Planner:
    """Hold, goto and trajectories planned and validated here, the other commands
    forwarded to the core; implements daemon.service.api.DaemonHandler.

    Building one loads the compiled kernels validation runs (load_checks: about a second
    the first time in a process): where a control cycle runs in the same process (the
    tests' in-process stacks), build it first."""

    def __init__(self, config: DaemonConfig, link: CoreLink) -> None:
        self.config = config
        self.robot = config.robot
        self.link = link
        self._wrench_check = daemon_wrench_check(config)
        load_checks(config)  # compiled now, not in a validation sharing a cycle's loop
        self._holds = 0  # hold commands so far: plans under way when one came are dropped
        # homing's offsets and the drives that lost theirs, kept in the state directory
        robot = config.robot
        identity = robot_identity(robot, config.drives)
        self.store = OffsetStore(config.state_dir, robot.name, robot.n_cables, identity)
        link.subscribe(self.store.on_event)
        # the payload freeze's and the observer hold's leases, timed here, not in the cycle
        self._sinks: list[EventSink] = []
        self.leases = Leases(link.command_keeping, self.emit, link.now)
        # the motion running and the client that owns it
        self.motions = Motions(link.now, self.emit)
        link.subscribe(self.motions.on_event)
        # what the companion adds of its own to every status reply and the state, by key
        # (the recordings: daemon.process.companion)
        self.reports: dict[str, Callable[[], Any]] = {}

    # -- DaemonHandler --------------------------------------------------------------------

    def command(self, name: str, args: dict[str, Any]) -> Awaitable[dict[str, Any]]:
        if name == "hold":
            return self._hold(Claim.of(args))
        if name == "goto":
            return self._goto(args)
        if name == "identify_payload":
            self.motions.check(name, Claim.of(args))
            self._require_moving("identify the payload")
            return self._procedure(name, args, lambda motion: identify_payload(self, args, motion))
        if name in ("home", "pretension"):
            self.motions.check(name, Claim.of(args))
            return self._procedure(name, args, lambda _motion: self._home(name, args))
        if name in HELD_BY:
            return self.leases.command(name, args)
        if name in STATUS_REPLIES:
            return self._status(name, args)
        return self.link.command(name, args)

    async def slack(self) -> None:
        await self.link.slack()

    def state(self) -> dict[str, Any]:
        # the core's snapshot (shared: not modified), the leases' time left, the motion,
        # the reports
        return {**self.link.state(), **self._own()}

    def subscribe(self, sink: EventSink) -> None:
        self._sinks.append(sink)
        self.link.subscribe(sink)

    def emit(self, event: dict[str, Any]) -> None:
        """An event of the planner's own (or the companion's), with the core's time and
        safety state as the core's events have them."""
        event.setdefault("t", self.link.now())
        event.setdefault("state", self.link.safety_state)
        for sink in self._sinks:
            sink(event)

    async def submit_trajectory(
        self, trajectory: Trajectory, start: float | None, claim: Claim = UNNAMED
    ) -> dict[str, Any]:
        """Validate and run `trajectory`, its times relative to `start` (a unix time it
        may not begin before, at most trajectory.max_start_delay ahead) or to now, after a
        smooth approach from the current reference.  Rejected: nothing changes and
        CommandError names the limit, the waypoint and the value; "not_owner" while
        another client's motion runs (unless `claim` preempts).  Until a later start's
        approach begins the robot carries on (HOLD, or TRACKING what runs); it is
        TRACKING from then until the trajectory ends."""
        self.motions.check("trajectory", claim)
        self._require_moving("run a trajectory")
        limits = self.config.trajectory
        if start is not None:
            if start < time.time() - 1e-3:
                raise CommandError("rejected", f"trajectory start {start:.3f} lies in the past")
            try:
                check_start_delay(start - time.time(), limits)
            except TrajectoryError as exc:
                raise rejection("trajectory", exc) from None
        config = self.config
        await self._validate(
            trajectory, "trajectory", config.reference_limits, config.reference_lengths
        )
        link = self.link

        async def plan(current: Reference, begin: float) -> Trajectory:
            not_before = begin if start is None else max(begin, link.now() + start - time.time())
            shifted = trajectory.shifted(not_before - trajectory.start_time)
            # first from where the current motion is at the start (at rest if it ends by
            # then): an approach that begins after the motion's end is found at once, not
            # after plans from states of the motion that may not reach it in the attempts
            state, _ = await link.reference_at(shifted.start_time)
            for _ in range(SETTLE_ATTEMPTS):
                planned = await link.run_steps(approach_steps(state, shifted, limits))
                if planned.start_time < begin:  # the blend would start in the past
                    return await link.run_steps(
                        approach_steps(current, shifted, limits, start=begin)
                    )
                # it begins later: from the state the reference has then, or it would jump
                then, _ = await link.reference_at(planned.start_time)
                if then.same_as(state):
                    return planned
                state = then
            raise TrajectoryError(
                "start",
                f"the current motion is still under way at t={planned.start_time:.6g} s, when "
                "the approach to this start would begin: start later, or hold first",
                waypoint=0,
            )

        return await self._plan_and_follow(plan, "trajectory", validate="blend", owner=claim)

    # -- planned commands -----------------------------------------------------------------

    async def _hold(self, claim: Claim) -> dict[str, Any]:
        """To rest as soon as the limits allow, never turning back (stop_steps);
        never refused for want of time (it tries again with longer leads), nor for whose
        the motion is (it ends it: `claim` stopped it).  The reply is the status, as
        `status` has it (with the leases and the motion)."""
        self._require_moving("hold")
        limits = self.config.trajectory

        async def stop(current: Reference, begin: float) -> Trajectory:
            return await link.run_steps(stop_steps(current, limits, start=begin))

        link = self.link
        self._holds += 1
        await self._plan_and_follow(
            stop, "hold", lead=HOLD_LEAD, validate="none", attempts=HOLD_ATTEMPTS
        )
        self.motions.stopped(claim)
        return await self._status()

    async def _status(
        self, name: str = "status", args: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """The core's reply to `name` (one of STATUS_REPLIES: its status after the
        command) with what the planner adds (`_own`), as the published state has it."""
        reply = await self.link.command(name, {} if args is None else args)
        return {**reply, **self._own()}

    def _own(self) -> dict[str, Any]:
        """What the status and the state add to the core's: the leases' time left, the
        motion running (what, its client) and the `reports`."""
        running = self.motions.running()
        motion = None if running is None else running.describe()
        reports = {key: report() for key, report in self.reports.items()}
        return {"leases": self.leases.remaining(), "motion": motion, **reports}

    async def _procedure(
        self, name: str, args: dict[str, Any], run: Callable[[Motion], Awaitable[Result]]
    ) -> Result:
        """Run the procedure `name` as the motion of its request's client (taken once it
        starts: a command the interface never starts takes nothing), until it ends."""
        motion = self.motions.take(name, Claim.of(args))
        try:
            return await run(motion)
        finally:
            self.motions.finish(motion)

    async def _home(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        """The core homes (home, or pretension at its end) and applies the offsets;
        they are stored here, also those of a pretension that aborted after its homing
        (the core keeps them in force, its refusal carries them:
        daemon.service.pretension_run.PretensionRun.finish)."""
        try:
            result = await self.link.command(name, args)
        except CommandError as exc:
            if "offsets" not in exc.details:
                raise
            kept = exc.details
            stored = await self.store.store(kept["offsets"], kept["method"])
            raise CommandError(exc.code, exc.reason, **kept, **stored) from None
        return {**result, **await self.store.store(result["offsets"], result["method"])}

    async def fly_to(self, pose: Pose, procedure: Motion) -> dict[str, Any]:
        """A goto to `pose` as a step of the running `procedure` (identify_payload):
        "preempted" if another motion replaced it."""
        return await self._goto({"pose": pose}, procedure)

    async def _goto(self, args: dict[str, Any], procedure: Motion | None = None) -> dict[str, Any]:
        """A goto of its own (its request's client's), or a step of `procedure`."""
        owner = Claim.of(args) if procedure is None else procedure
        if isinstance(owner, Claim):
            self.motions.check("goto", owner)
        self._require_moving("goto")
        target = args.get("pose")
        if not isinstance(target, Pose):
            raise CommandError("bad_request", "goto needs a target pose")
        limits = self.config.trajectory
        link = self.link

        async def plan(current: Reference, begin: float) -> Trajectory:
            return await link.run_steps(goto_steps(current, target, limits, start=begin))

        return await self._plan_and_follow(plan, "goto", owner=owner, target=target)

    async def _validate(
        self,
        trajectory: Trajectory,
        what: str,
        pose_limits: PoseLimits,
        length_limits: LengthLimits,
        segments: int | None = None,
    ) -> None:
        """DESIGN §7 validation (of the first `segments` only, if given); every sampled
        pose inside `pose_limits`, its cable lengths inside `length_limits`."""
        steps = validation_steps(
            trajectory,
            self.robot,
            self.config.trajectory,
            self._wrench_check,
            pose_limits,
            length_limits,
            segments,
            self._workspace(),
        )
        try:
            await self.link.run_steps(steps)
        except TrajectoryError as exc:
            raise rejection(what, exc) from None

    def _check_target(
        self, target: Pose, what: str, pose_limits: PoseLimits, length_limits: LengthLimits
    ) -> None:
        """CommandError "rejected" if resting at `target` breaks a limit (check_target)."""
        try:
            check_target(
                target,
                self.robot,
                self.config.trajectory,
                self._wrench_check,
                pose_limits,
                length_limits,
                self._workspace(),
            )
        except TrajectoryError as exc:
            raise rejection(what, exc) from None

    def _workspace(self) -> WorkspaceCheck:
        """The workspace check (daemon.config.workspace) for the platform as the core
        last published it: the payload estimate's mass and centre of mass, else the
        robot file's."""
        check = self.config.workspace_check
        payload = self.link.state().get("payload")
        if not payload:
            return check
        return check.carrying(payload["mass"], payload["center_of_mass"])

    async def _plan_and_follow(
        self,
        make: Callable[[Reference, float], Awaitable[Trajectory]],
        what: str,
        lead: float = PLANNING_LEAD,
        validate: Literal["all", "blend", "none"] = "all",
        attempts: int = 3,
        owner: Claim | Motion | None = None,
        target: Pose | None = None,
    ) -> dict[str, Any]:
        """A transition from the current reference, planned to begin `lead` seconds
        ahead, validated and handed to the core; planned again if the core's reference
        changed meanwhile, or with a longer lead if the work outlasted it (three times as
        long, at least twice what the late attempt took; `attempts` in all, then
        CommandError "busy").  `validate`: the whole result, only its first
        segment (the rest already was), or nothing (a hold: stopping may not be refused);
        inside the validation pose limits, or no further out than where the transition
        starts (it may start outside them).  `owner`: the claim the transition runs for
        (a motion of its own, taken when the core takes it: daemon.service.motion), the
        procedure it is a step of, or None (a hold).  `target`: where it ends at rest,
        checked before the way to it (check_target: a goto names its target's problem)."""
        holds = self._holds
        link = self.link
        for _ in range(attempts):
            asked = link.now()
            begin = asked + lead
            current, version = await link.reference_at(begin)
            try:
                planned = await make(current, begin)
            except TrajectoryError as exc:
                raise rejection(what, exc) from None
            if validate != "none":
                begins = planned.knot(0).pose  # not .waypoints: all of them made
                inside = self.config.reference_limits.widened_to(begins)
                reach = self.config.reference_lengths.widened_to(
                    self.robot.cable_lengths(begins).tolist()
                )
                if target is not None:
                    self._check_target(target, what, inside, reach)
                if validate == "blend":  # its end may be moving: checked in place
                    leads = max(planned.lead_segments, 1)  # a ramp's too (transitions)
                    await self._validate(planned, f"{what}'s approach", inside, reach, leads)
                else:
                    await self._validate(planned, what, inside, reach)
            if self._holds != holds and what != "hold":
                raise CommandError("invalid_state", f"{what} dropped: a hold came meanwhile")
            reply = await self._follow(planned, version, what, owner)
            replan = reply.get("replan")
            if replan is None:
                return reply
            if replan == "late":
                # the next lead outlasts this attempt twice over: on a host where this
                # process went unscheduled for a while, tripling alone may never catch up
                lead = max(3 * lead, 2.0 * (link.now() - asked), MIN_LEAD)
        raise CommandError("busy", f"{what}: planning kept outlasting its lead")

    async def _follow(
        self, planned: Trajectory, version: int, what: str, owner: Claim | Motion | None
    ) -> dict[str, Any]:
        """Hand `planned` to the core as `owner`'s motion (see _plan_and_follow): the
        core's reply."""
        if isinstance(owner, Motion):
            self.motions.owns(owner)
        if not isinstance(owner, Claim):
            return await self.link.follow(planned, version, what)
        motion = self.motions.take(what, owner)
        try:
            reply = await self.link.follow(planned, version, what)
        except BaseException:
            self.motions.restore(motion)
            raise
        if reply.get("replan") is None:
            self.motions.commit(motion, reply["end"])
        else:
            self.motions.restore(motion)
        return reply

    def _require_moving(self, action: str) -> None:
        state = self.link.safety_state
        if state not in MOVING:
            raise CommandError("invalid_state", f"cannot {action} while {state} (enable first)")


class LocalLink:
    """A CoreLink to a Service on the same event loop: planning and validation run in
    the cycle's slack (Service.in_slack), so that they never delay the cycle."""

    def __init__(self, service: Any) -> None:
        self.service = service

    def now(self) -> float:
        return self.service.now()

    @property
    def safety_state(self) -> str:
        return self.service.machine.state.value

    async def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        result = self.service.command(name, args)
        return (await result) if isinstance(result, Awaitable) else result

    async def command_keeping(
        self, name: str, args: dict[str, Any], leases: Kept
    ) -> dict[str, Any]:
        return await self.command(name, args)  # one process: no later companion to keep them for

    async def reference_at(self, t: float) -> tuple[Reference, int]:
        return self.service.reference_at(t)

    async def follow(self, trajectory: Trajectory, version: int, what: str) -> dict[str, Any]:
        return self.service.follow_planned(trajectory.curve, version, what)

    async def run_steps(self, steps: Generator[Any, None, Result]) -> Result:
        return await self.service.in_slack(steps)

    def state(self) -> dict[str, Any]:
        return self.service.state()

    async def slack(self) -> None:
        await self.service.slack()

    def subscribe(self, sink: EventSink) -> None:
        self.service.subscribe(sink)
