"""The robot's homing and calibration state on disk (DESIGN §15 step 3, §19).

One JSON file per robot in the state directory (`state_dir`; under systemd the unit's
StateDirectory=, /var/lib/cdprd): each drive's length offset (m, the cable length at
motor position 0; it replaces drives.length_offset), whether it still holds (a drive that
rebooted or lost its position since invalidates its own, with the reason), when and how
it was found.  Written atomically (a temporary file in the same directory, fsync,
rename, fsync of the directory): a crash leaves the old file or the new one, never a
torn one.  A file that cannot be read is a StateFileError naming the file and the
problem; it is never overwritten: `set_aside` renames it before a new state is written.

A state file is data from disk, not a fact about the robot, so it carries what lets the
daemon refuse one that is not this robot's own, unchanged (schema 2):
- `identity`: a digest of what the offsets are measured against (`robot_identity`: each
  cable's anchor, attachment and pulley, each drive's node and length scaling).  A file
  restored from another robot, or left from before the robot file or the drives changed,
  is refused.
- `checksum`: SHA-256 of the rest of the content (canonical JSON): an edited or damaged
  file is refused.
A schema 1 file (from before both) cannot be checked and is refused, asking for homing.
A refused file leaves every offset invalid (enable refused until homed: the daemon
starts, braked or idle, and `home` writes a new file, setting the refused one aside).
Even a file that passes is checked against the robot at enable (daemon.service.rest_check).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from cdpr.robot import Robot
from cdpr.trusted_file import UnreadableFileError, read_trusted
from drivers.config import DrivesConfig

log = logging.getLogger("cdprd")

SCHEMA = 2
MAX_BYTES = 1 << 16
REHOME = "home again (cdprd home) to find the offsets afresh"


class StateFileError(RuntimeError):
    """The state file exists but cannot be used (names the file and the problem)."""


@dataclass(frozen=True)
class CalibrationState:
    """offsets[k]: drive k's length offset (m); invalid[k]: why it no longer holds
    (None: it holds); time: unix seconds it was found; method: how ("home at pose
    home", "calibrate ...")."""

    robot: str
    identity: str  # robot_identity of the robot and drives the offsets belong to
    offsets: tuple[float, ...]
    invalid: tuple[str | None, ...]
    time: float
    method: str

    def invalidated(self, drive: int, why: str) -> CalibrationState:
        """This state with drive `drive`'s offset marked as lost, for `why`."""
        invalid = list(self.invalid)
        invalid[drive] = why
        return replace(self, invalid=tuple(invalid))


def state_path(state_dir: Path, robot: str) -> Path:
    """The state file of robot `robot` in `state_dir`."""
    return state_dir / f"{robot}.calibration.json"


def robot_identity(robot: Robot, drives: DrivesConfig) -> str:
    """A digest of what stored offsets are measured against: the robot's name, each
    cable's anchor, attachment and pulley, and each drive's node and length scaling (drum
    radius or spool, gear ratio, encoder resolution, direction; not its configured
    offset, which the stored one replaces).  The platform's inertia, the limits and the
    gains do not change what an offset means, and are left out."""
    scalings = [replace(s, length_offset=0.0) for s in drives.scalings_for(robot)]
    facts = {
        "robot": robot.name,
        "cables": [c.model_dump(mode="json", include={"anchor", "attachment", "pulley"})
                   for c in robot.spec.cables],
        "nodes": list(drives.nodes),
        "scalings": [repr(s) for s in scalings],
    }
    return checksum(facts)


def new_state(robot: str, identity: str, offsets: list[float], method: str) -> CalibrationState:
    """Every offset valid, found now by `method`."""
    n = len(offsets)
    return CalibrationState(robot, identity, tuple(offsets), (None,) * n, time.time(), method)


def checksum(body: Any) -> str:
    """SHA-256 of `body` as canonical JSON ("sha256:..."): what a checked file carries
    to show it is unedited and undamaged; ValueError on a NaN or infinity."""
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return "sha256:" + hashlib.sha256(canonical.encode()).hexdigest()


def load_state(path: Path, robot: str, n: int, identity: str) -> CalibrationState | None:
    """The state in `path` (None: there is none), for robot `robot` with n drives and
    `identity` (robot_identity); StateFileError names the file and what is wrong with it."""
    if not os.path.lexists(path):
        return None
    try:
        raw = read_trusted(path, MAX_BYTES)
    except UnreadableFileError as exc:
        raise StateFileError(str(exc)) from None
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise StateFileError(f"{path}: corrupt (not JSON: {exc})") from None
    return _parse(data, path, robot, n, identity)


def _parse(data: Any, path: Path, robot: str, n: int, identity: str) -> CalibrationState:
    def bad(key: str, problem: str) -> StateFileError:
        return StateFileError(f"{path}: {key}: {problem}")

    if not isinstance(data, dict):
        raise bad("(top)", f"expected an object, got {type(data).__name__}")
    if data.get("schema") == 1:
        raise bad(
            "schema",
            "1, written before state files carried a checksum and the robot's identity: it "
            f"cannot be checked; {REHOME}",
        )
    if data.get("schema") != SCHEMA:
        raise bad("schema", f"expected {SCHEMA}, got {data.get('schema')!r}")
    body = {k: v for k, v in data.items() if k != "checksum"}
    try:
        expected = checksum(body)
    except ValueError:  # a NaN or infinity: not what save_state writes
        expected = None
    if data.get("checksum") != expected:
        raise bad("checksum", f"does not match the content (edited or damaged); {REHOME}")
    if data.get("robot") != robot:
        raise bad("robot", f"the state of robot {data.get('robot')!r}, not of {robot!r}")
    if data.get("identity") != identity:
        raise bad(
            "identity",
            "the offsets of another robot, or of this one before its robot file (anchors, "
            "attachments, pulleys, drums) or its drives (nodes, gear ratio, encoder "
            f"resolution, direction) changed; {REHOME}",
        )
    offsets = data.get("offsets")
    if not (
        isinstance(offsets, list)
        and len(offsets) == n
        and all(type(x) in (int, float) and math.isfinite(x) for x in offsets)
    ):
        raise bad("offsets", f"expected {n} finite numbers (m), one per drive")
    invalid = data.get("invalid")
    if not (
        isinstance(invalid, list)
        and len(invalid) == n
        and all(x is None or isinstance(x, str) for x in invalid)
    ):
        raise bad("invalid", f"expected {n} entries, each null or a reason")
    stamp, method = data.get("time"), data.get("method")
    if type(stamp) not in (int, float) or not math.isfinite(stamp):
        raise bad("time", "expected unix seconds")
    if not isinstance(method, str):
        raise bad("method", "expected a string")
    return CalibrationState(
        robot, identity, tuple(float(x) for x in offsets), tuple(invalid), float(stamp), method
    )


def save_state(path: Path, state: CalibrationState) -> None:
    """Write `state` to `path` atomically (module docstring); OSError if it cannot."""
    body = {"schema": SCHEMA, **asdict(state)}
    body["offsets"], body["invalid"] = list(state.offsets), list(state.invalid)
    body["checksum"] = checksum(body)
    write_atomically(path, (json.dumps(body, indent=1) + "\n").encode())


def write_atomically(path: Path, data: bytes) -> None:
    """Write `data` to `path` so that a crash leaves the old file or the new one, never a
    torn one (module docstring); OSError if it cannot."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def set_aside(path: Path) -> Path:
    """Rename an unreadable state file out of the way (kept, never overwritten): the
    new name, `<name>.corrupt-<unix time>`."""
    aside = path.with_name(f"{path.name}.corrupt-{int(time.time())}")
    os.replace(path, aside)
    return aside


class OffsetStore:
    """What homing and calibration find, and each drive that lost its offset since, kept
    in the state directory (None: in memory only; the core holds the offsets in force).
    Runs beside the planner (the companion), never in the control cycle: writes go to a
    worker thread."""

    def __init__(self, state_dir: Path | None, robot: str, n: int, identity: str) -> None:
        self.path = None if state_dir is None else state_path(state_dir, robot)
        self.robot, self.n, self.identity = robot, n, identity

    async def store(self, offsets: list[float], method: str) -> dict[str, Any]:
        """Keep `offsets` found by `method`, every one valid: where they went (and an
        unreadable file set aside, if there was one)."""
        if self.path is None:
            return {"stored": None, "note": "no state_dir: kept until the daemon stops"}
        state = new_state(self.robot, self.identity, offsets, method)
        return await asyncio.to_thread(self._replace, state)

    def on_event(self, event: dict[str, Any]) -> None:
        """A core event; an "offset_lost" one is written down (a daemon started later
        must not trust that offset either)."""
        if event.get("event") != "offset_lost" or self.path is None:
            return
        drive, why = int(event["drive"]), str(event["why"])
        asyncio.get_running_loop().run_in_executor(None, self._invalidate, drive, why)

    def _replace(self, state: CalibrationState) -> dict[str, Any]:
        assert self.path is not None
        reply: dict[str, Any] = {"stored": str(self.path)}
        try:
            load_state(self.path, self.robot, self.n, self.identity)
        except StateFileError:
            reply["set_aside"] = str(set_aside(self.path))
        save_state(self.path, state)
        return reply

    def _invalidate(self, drive: int, why: str) -> None:
        assert self.path is not None
        try:
            state = load_state(self.path, self.robot, self.n, self.identity)
            if state is not None:
                save_state(self.path, state.invalidated(drive, why))
        except (StateFileError, OSError) as exc:  # the core refuses enable all the same
            log.error("calibration state: could not record drive %d's lost offset: %s", drive, exc)
