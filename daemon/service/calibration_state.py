"""The robot's homing and calibration state on disk (DESIGN §15 step 3).

One JSON file per robot in the state directory (`state_dir`; under systemd the unit's
StateDirectory=, /var/lib/cdprd): each drive's length offset (m, the cable length at
motor position 0; it replaces drives.length_offset), whether it still holds (a drive that
rebooted or lost its position since invalidates its own, with the reason), when and how
it was found.  Written atomically (a temporary file in the same directory, fsync,
rename, fsync of the directory): a crash leaves the old file or the new one, never a
torn one.  A file that cannot be read is a StateFileError naming the file and the
problem; it is never overwritten: `set_aside` renames it before a new state is written.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

log = logging.getLogger("cdprd")

SCHEMA = 1
MAX_BYTES = 1 << 16


class StateFileError(RuntimeError):
    """The state file exists but cannot be used (names the file and the problem)."""


@dataclass(frozen=True)
class CalibrationState:
    """offsets[k]: drive k's length offset (m); invalid[k]: why it no longer holds
    (None: it holds); time: unix seconds it was found; method: how ("home at pose
    home", "calibrate ...")."""

    robot: str
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


def new_state(robot: str, offsets: list[float], method: str) -> CalibrationState:
    """Every offset valid, found now by `method`."""
    return CalibrationState(robot, tuple(offsets), (None,) * len(offsets), time.time(), method)


def load_state(path: Path, robot: str, n: int) -> CalibrationState | None:
    """The state in `path` (None: there is none), for robot `robot` with n drives;
    StateFileError names the file and what is wrong with it."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise StateFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(raw) > MAX_BYTES:
        raise StateFileError(f"{path}: larger than {MAX_BYTES} bytes: not a state file")
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise StateFileError(f"{path}: corrupt (not JSON: {exc})") from None
    return _parse(data, path, robot, n)


def _parse(data: Any, path: Path, robot: str, n: int) -> CalibrationState:
    def bad(key: str, problem: str) -> StateFileError:
        return StateFileError(f"{path}: {key}: {problem}")

    if not isinstance(data, dict):
        raise bad("(top)", f"expected an object, got {type(data).__name__}")
    if data.get("schema") != SCHEMA:
        raise bad("schema", f"expected {SCHEMA}, got {data.get('schema')!r}")
    if data.get("robot") != robot:
        raise bad("robot", f"the state of robot {data.get('robot')!r}, not of {robot!r}")
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
        robot, tuple(float(x) for x in offsets), tuple(invalid), float(stamp), method
    )


def save_state(path: Path, state: CalibrationState) -> None:
    """Write `state` to `path` atomically (module docstring); OSError if it cannot."""
    body = {"schema": SCHEMA, **asdict(state)}
    body["offsets"], body["invalid"] = list(state.offsets), list(state.invalid)
    data = (json.dumps(body, indent=1) + "\n").encode()
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

    def __init__(self, state_dir: Path | None, robot: str, n: int) -> None:
        self.path = None if state_dir is None else state_path(state_dir, robot)
        self.robot, self.n = robot, n

    async def store(self, offsets: list[float], method: str) -> dict[str, Any]:
        """Keep `offsets` found by `method`, every one valid: where they went (and an
        unreadable file set aside, if there was one)."""
        if self.path is None:
            return {"stored": None, "note": "no state_dir: kept until the daemon stops"}
        return await asyncio.to_thread(self._replace, new_state(self.robot, offsets, method))

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
            load_state(self.path, self.robot, self.n)
        except StateFileError:
            reply["set_aside"] = str(set_aside(self.path))
        save_state(self.path, state)
        return reply

    def _invalidate(self, drive: int, why: str) -> None:
        assert self.path is not None
        try:
            state = load_state(self.path, self.robot, self.n)
            if state is not None:
                save_state(self.path, state.invalidated(drive, why))
        except (StateFileError, OSError) as exc:  # the core refuses enable all the same
            log.error("calibration state: could not record drive %d's lost offset: %s", drive, exc)
