"""The pretension command in the core: from slack cables on a docking fixture to the
position loop (cdpr.pretension), a procedure the control cycle drives
(daemon.service.procedure.CycleProcedure).

The command enables the drives in force and puts the robot in PRETENSION; from then the
cycle hands each cycle's lengths to `cycle`, which steps cdpr.pretension's wind, ramp
and settle and sends its forces; settled, it homes at the fixture's pose with the settled
lengths and, once the cycle has trusted the homed lengths, the command closes the loop
there (HOLD), the fixture's share of the weight handed over to the controller for
unload_time (`before_step`).  The reply comes when the first command of the loop has
gone out (its step from the last pretension force: `loop_close_step_n`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr.homing import homed_offsets
from cdpr.pretension import Pretension, ramp_target
from daemon.service.api import CommandError
from daemon.service.rest import named_pose, require_unpowered
from daemon.service.safety import Fault, SafetyState, Trigger
from daemon.service.trusted_lengths import RETRUST_CYCLES
from drivers.base import DriverError, FrameError

if TYPE_CHECKING:
    from daemon.service.service import Service

log = logging.getLogger("cdprd")


async def pretension(core: Service, args: dict[str, Any]) -> dict[str, Any]:
    """Bring the platform resting on a fixture at the robot file's pose (args
    "pose_name", default home) from slack cables to the position loop (module
    docstring).  From IDLE, or BRAKED where the only conditions are lengths that fit no
    pose (slack cables at start-up).  The reply comes when the loop has closed (HOLD);
    CommandError naming the reason if it aborted (braked)."""
    require_unpowered(core, "pretension")
    blocking = [f for f in core.faults if f.trigger is not Trigger.IMPLAUSIBLE_FEEDBACK]
    if blocking:
        raise CommandError(
            "invalid_state", "cannot pretension: " + "; ".join(f.message for f in blocking)
        )
    name, pose = named_pose(core.robot, "pretension", args)
    raw = [fb.length for fb in core.driver.feedback]
    if not all(map(math.isfinite, raw)):
        raise CommandError("invalid_state", "pretension: no feedback from every drive yet")
    spec, solver = core.config.pretension, core.controller.tension
    try:
        target = ramp_target(core.robot, solver, pose, spec.carry)
        planned = Pretension(
            core.robot, spec, pose, target, core.controller.stretch.scale, core.offsets.read(raw)
        )
    except ValueError as exc:
        raise CommandError("rejected", f"pretension at pose {name}: {exc}") from None
    brakes = core.brakes
    with core.drives_busy():
        try:
            await core.driver.enable(core.port, raw, planned.forces.tolist())
        except DriverError as exc:
            core.brake(Fault(Trigger.DRIVE_FAULT, f"pretension: enable failed: {exc}"))
            raise CommandError("drive_error", f"pretension: enable failed: {exc}") from None
    if core.brakes != brakes:  # braked meanwhile (maybe braked again)
        raise CommandError("invalid_state", f"pretension aborted: {core.machine.fault.line()}")
    run = PretensionRun(core, name, planned)
    core.procedure, core.pretension = run, planned
    core.machine.pretension()
    core.emit({"event": "state", "why": f"pretension at pose {name}"})
    # the rest runs to its end even if the caller goes away (a cancelled command would
    # leave the robot in PRETENSION, the loop never closed)
    return await asyncio.shield(asyncio.ensure_future(run.finish()))


class PretensionRun:
    """One pretension after its drives enabled: the cycles it drives, its homing, the
    loop's closing and the command's reply (`finish`)."""

    def __init__(self, core: Service, name: str, pretension: Pretension) -> None:
        self.core = core
        self.name = name  # its pose's name
        self.pretension = pretension
        self.changes: list[float] = []  # mm, the offsets' changes at its homing (once homed)
        self.loop_close_step: float | None = None  # N, the largest force change at close
        self._close_forces: np.ndarray | None = None  # the last before it, until measured
        self._cycles = 0  # cycles waited for the homed lengths to be judged
        # homed and the homed lengths trusted, or braked
        self._homed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    @property
    def winding(self) -> bool:
        return self.pretension.active

    def cycle(self, t: float, lengths: list[float], rates: list[float]) -> None:
        """One cycle of PRETENSION: cdpr.pretension's forces while it winds, ramps and
        settles; then homing at its pose, and once the homed lengths are trusted (one
        pose, the cycle's check) `finish` is woken to close the loop."""
        core, p = self.core, self.pretension
        if p.active:
            try:
                p.step(t, lengths, rates)
            except Exception as exc:
                log.exception("pretension step raised")
                core.brake(Fault(Trigger.CONTROLLER_EXCEPTION, f"{type(exc).__name__}: {exc}"))
                return
            if p.fault is not None:
                core.brake(Fault(Trigger.PRETENSION, p.fault))
                return
            if p.phase == "done":
                self._home()
        try:
            core.send(core.driver.commands(p.forces))
        except FrameError as exc:
            core.brake(Fault(Trigger.NAN, str(exc)))
            return
        if p.phase != "done":
            return
        if not core.trust.retrusting:
            self._wake()  # `finish` closes the loop (off the cycle)
            return
        self._cycles += 1
        if self._cycles > RETRUST_CYCLES:
            core.brake(Fault(Trigger.PRETENSION, "the homed lengths were never judged"))

    def before_step(self, t: float) -> None:
        p = self.pretension
        if p.phase == "unload":
            p.unload(self.core.controller, t)

    def after_commands(self, commands: np.ndarray) -> None:
        if self._close_forces is not None:  # the first command after pretension
            self.loop_close_step = float(np.abs(commands - self._close_forces).max())
            self._close_forces = None

    def end(self, why: str) -> None:
        self._wake()
        p = self.pretension
        if p.phase not in ("closed", "aborted"):
            p.phase, p.fault = "aborted", p.fault or why
        self._close_forces = None  # the loop did not close: no step to measure

    def _wake(self) -> None:
        if not self._homed.done():
            self._homed.set_result(None)

    def _home(self) -> None:
        """Home at the pretension's pose with its settled lengths and tensions."""
        core, p = self.core, self.pretension
        assert p.settled_lengths is not None
        driver = np.array(core.offsets.write(p.settled_lengths.tolist()))
        offsets = homed_offsets(
            core.robot, p.pose, p.planned, core.controller.stretch.scale, driver,
            np.array(core.offsets.configured),
        )  # fmt: skip
        name = self.name
        changes = core.offsets.set(offsets.tolist(), f"pretension at pose {name}", time.time())
        core.trust.shift(changes)
        self.changes = [c * 1e3 for c in changes]
        log.info("pretension at pose %s: homed, offsets changed by %s mm", name,
                 [round(c * 1e3, 2) for c in changes])  # fmt: skip
        core.emit({"event": "homed", "pose": name})

    def _close_loop(self) -> None:
        """The pretension's end: the pose measured from the homed lengths under its
        tensions (as enable does), the loop closed there with the fixture's share preset
        (Pretension.close); the next cycle is the controller's, and `after_commands`
        measures how far its commands differ from the last ones (loop_close_step)."""
        core, p = self.core, self.pretension
        try:
            pose = core.measured_pose(lambda pose: p.planned)
        except CommandError as exc:
            core.brake(Fault(Trigger.PRETENSION, f"after homing: {exc.reason}"))
            return
        self._close_forces = p.forces.copy()
        p.close(core.controller, pose, core.now())
        core.source_changed()
        core.machine.go("tensioned")
        core.emit({"event": "state", "why": "pretension done: position loop closed"})

    async def finish(self) -> dict[str, Any]:
        """Once homed (or braked): close the loop, wait for the first cycle in HOLD, and
        reply (or CommandError naming the abort).  Aborted after its homing (braked
        before the loop closed), the offsets it homed stay in force: they were found at
        rest on the fixture, as `home` finds them, and changing them under the brake
        would move the lengths it holds.  The refusal carries them ("offsets",
        "method") for the planner to store: the next start-up must read the offsets that
        were in force."""
        core = self.core
        await self._homed
        if core.machine.state is SafetyState.PRETENSION:
            self._close_loop()
        for _ in range(RETRUST_CYCLES):  # the first cycle in HOLD measures the step
            if self.loop_close_step is not None or not core.machine.moving:
                break
            await asyncio.sleep(core.period)
        offsets = core.offsets
        if not core.machine.moving:
            fault = core.machine.fault
            why = fault.line() if fault is not None else core.machine.state.value
            homed = bool(self.changes) and offsets.refusal() is None
            kept = {"offsets": offsets.offsets, "method": offsets.method} if homed else {}
            raise CommandError("rejected", f"pretension aborted: {why}", **kept)
        return {
            **core.status(),
            "offsets": offsets.offsets,
            "changes_mm": self.changes,
            "method": offsets.method,
            "time": offsets.time,
            "pose": self.name,
            "loop_close_step_n": self.loop_close_step,
        }
