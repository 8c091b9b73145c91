"""The platform at rest, seen from the core: feedback sampled until the cables rest, the
rest check of a pose against the tensions the drives measure there
(daemon.service.rest_check, which enable runs too), and the home command built on them
(DESIGN §15 step 3): every cable's length offset set so that the lengths read equal the
model's at a named resting pose (cdpr.homing).

Each function takes the service (daemon.service.service.Service) it runs in, between
cycles, and reads the cycles' feedback as it comes.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr import Pose, Robot
from cdpr.controller import static_tensions
from cdpr.homing import homed_offsets
from daemon.service.api import CommandError
from daemon.service.rest_check import judge
from daemon.service.safety import SafetyState
from drivers.base import DriverError

if TYPE_CHECKING:
    from daemon.service.service import Service

log = logging.getLogger("cdprd")

HOME_SAMPLES = 50  # cycles of feedback homing averages, each checked for rest
REST_RATE = 2e-3  # m/s: a cable moving faster is not at rest (homing is refused)
REST_SPREAD = 5e-4  # m: nor one whose length varies more over the samples
REST_SETTLE = 3.0  # s the cables may take to come to rest once the drives hold them
FORCE_READINGS = 10  # of the drives' measured forces, averaged for the rest check


def require_unpowered(core: Service, action: str) -> None:
    """CommandError unless the drives follow no forces (IDLE or BRAKED), where home and
    pretension begin: the controller's lengths must not jump under them."""
    state = core.machine.state
    if state not in (SafetyState.IDLE, SafetyState.BRAKED):
        raise CommandError(
            "invalid_state", f"cannot {action} while {state.value} (needs idle or braked)"
        )


def named_pose(robot: Robot, what: str, args: dict[str, Any]) -> tuple[str, Pose]:
    """The robot file's pose args["pose_name"] (default home) and its name;
    CommandError naming the poses there are for an unknown one."""
    name = str(args.get("pose_name") or "home")
    pose = robot.poses.get(name)
    if pose is None:
        raise CommandError(
            "bad_request",
            f"{what}: no pose {name!r} in the robot file (poses: {', '.join(robot.poses)})",
            field="pose",
        )
    return name, pose


async def rest_samples(core: Service, what: str = "home") -> list[list[float]]:
    """HOME_SAMPLES cycles of driver lengths; CommandError naming the drive if any
    moves (its lengths' trend above REST_RATE, or their spread above REST_SPREAD:
    the trend, a least-squares slope over the samples, not the reported rates, whose
    mean carries each rate's own noise: 20 um of encoder noise differenced over 2 ms
    read as 2.5 mm/s) or reports nothing."""
    lengths, rates = [], []
    for _ in range(HOME_SAMPLES):
        await asyncio.sleep(core.period)
        feedback = core.driver.feedback
        lengths.append([fb.length for fb in feedback])
        rates.append([fb.rate for fb in feedback])
    samples = np.asarray(lengths)
    reported = np.isfinite(samples).all(axis=0) & np.isfinite(rates).all(axis=0)
    if not reported.all():
        raise CommandError(
            "invalid_state", f"{what}: no feedback from drive {int(np.argmin(reported))}"
        )
    t = np.arange(HOME_SAMPLES) * core.period
    t -= t.mean()
    trend = np.abs(t.dot(samples - samples.mean(axis=0)) / t.dot(t))
    spread = np.ptp(samples, axis=0)
    k = int(np.argmax(trend))
    node = core.offsets.nodes
    if trend[k] > REST_RATE:
        raise CommandError(
            "invalid_state",
            f"{what}: the platform is not at rest: drive {k} (node {node[k]}) moves at "
            f"{trend[k] * 1e3:.2f} mm/s over {HOME_SAMPLES} cycles (at rest: below "
            f"{REST_RATE * 1e3:g} mm/s)",
        )
    k = int(np.argmax(spread))
    if spread[k] > REST_SPREAD:
        raise CommandError(
            "invalid_state",
            f"{what}: the platform is not at rest: drive {k} (node {node[k]}) length varied "
            f"by {spread[k] * 1e3:.2f} mm over {HOME_SAMPLES} cycles (at rest: below "
            f"{REST_SPREAD * 1e3:g} mm)",
        )
    noisy = core.noise.take(samples)
    if noisy is not None:
        log.warning("%s: %s", what, noisy["message"])
        core.emit(noisy)
    return lengths


async def rest_refusal(core: Service, pose: Pose, what: str) -> str | None:
    """With every drive holding its position: once the cables are at rest, why the
    tensions the drives measure cannot hold the platform at `pose`
    (daemon.service.rest_check); None if they can, or if the drives measure no force
    (the FK residual is then the only check, as the log says)."""
    if not core.driver.measures_force:
        log.warning(
            "%s: the drives measure no force: the pose is not checked by the "
            "tensions at rest, only by the FK residual",
            what,
        )
        return None
    end = core.now() + REST_SETTLE
    while True:  # the hold takes the load from the brake: the cables settle first
        try:
            await rest_samples(core, what)
            break
        except CommandError:
            if core.now() > end:
                raise
    forces = []  # averaged: one reading catches the hold's servo mid-correction
    for _ in range(FORCE_READINGS):
        forces.append(await core.driver.measured_forces(core.port))
        await asyncio.sleep(core.period)
    forces = np.mean(forces, axis=0).tolist()
    safety = core.config.safety
    residual, refusal = judge(core.robot, pose, forces, safety.rest_force, safety.rest_torque)
    log.info("%s: rest check at %s: %s", what, position_text(pose), residual.text())
    return refusal


async def home(core: Service, args: dict[str, Any]) -> dict[str, Any]:
    """The home command: the offsets that put the platform at the named pose, once it
    is seen at rest over HOME_SAMPLES cycles (and, where the drives measure force, its
    tensions hold it there).  Only while the drives are not following forces (IDLE or
    BRAKED): the controller's lengths must not jump under it."""
    require_unpowered(core, "home")
    name, pose = named_pose(core.robot, "home", args)
    with core.drives_busy():
        samples = await rest_samples(core)
        if core.driver.measures_force:
            await _home_rest_check(core, name, pose, np.mean(samples, axis=0).tolist())
            samples = await rest_samples(core)  # where the brake holds it now
    lengths = np.mean(samples, axis=0)
    tensions = static_tensions(core.robot, core.controller.tension, pose)
    configured = np.array(core.offsets.configured)
    offsets = homed_offsets(
        core.robot, pose, tensions, core.controller.stretch.scale, lengths, configured
    )
    method = f"home at pose {name}"
    changes = core.offsets.set(offsets.tolist(), method, time.time())
    core.trust.shift(changes)
    moved = [round(c * 1e3, 2) for c in changes]
    log.info("homed at pose %s: offsets changed by %s mm", name, moved)
    core.emit({"event": "homed", "pose": name})
    return {
        "offsets": core.offsets.offsets,
        "changes_mm": [c * 1e3 for c in changes],
        "method": method,
        "time": core.offsets.time,
        "pose": name,
    }


async def _home_rest_check(core: Service, name: str, pose: Pose, lengths: list[float]) -> None:
    """CommandError unless the platform can be resting at `pose`: the drives hold
    `lengths` (driver lengths, where they are at rest) while they measure the
    tensions, which must hold the platform at `pose` (rest_refusal); then the brake, at
    the trusted lengths or, for a cable with none (braked on implausible feedback),
    where its drive holds it now: a drive without a length would be switched off, and
    without a holding brake its drum would free-wheel."""
    brakes = core.brakes
    trusted = core.hold_lengths()
    held = [h if math.isfinite(h) else x for h, x in zip(trusted, lengths, strict=True)]
    try:
        await core.driver.enable(core.port, lengths, [0.0] * core.n)
        refusal = await rest_refusal(core, pose, "home")
    except DriverError as exc:
        raise CommandError(
            "drive_error", f"home: the drives cannot hold to measure the tensions: {exc}"
        ) from None
    finally:
        if core.brakes == brakes:  # a brake meanwhile sent its own frames
            core.send_brake(held)
    if core.brakes != brakes:
        raise CommandError("invalid_state", f"home aborted: {core.machine.fault.line()}")
    if refusal is not None:
        log.error("home at pose %s refused: %s", name, refusal)
        raise CommandError(
            "rejected", f"home: the platform is not resting at pose {name!r}: {refusal}"
        )


def position_text(pose: Pose) -> str:
    """A pose's reference point as messages print it."""
    x, y, z = pose.position_tuple
    return f"({x:.3f}, {y:.3f}, {z:.3f}) m"
