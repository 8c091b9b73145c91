"""A calibration round on disk: the poses `cdprd calibrate` planned and each one it has
recorded so far, kept so that a round a brake (or SIGTERM, or a lost lease) interrupts
is continued with `cdprd calibrate --resume` instead of flown again from the start.

One JSON file per robot, `ROBOT.calibration-round.json` in the config's state_dir (or,
without one, beside the robot file), written atomically (the way the stored offsets are:
daemon.service.calibration_state.write_atomically) when the round is planned and after
every pose, and removed once every planned pose has been flown and solved.  Like the
stored offsets it is data from disk, checked before it is used (schema 1):
- `identity`: robot_identity of the robot file and drives the lengths were read with: a
  round from another robot, or from before its robot file or drives changed, is refused;
- `offsets`: the daemon's offsets in force when the lengths were read (m per drive); a
  round continues only while the daemon has the same ones (homing again changes what
  every length read means);
- `checksum`: SHA-256 of the rest (canonical JSON): an edited or damaged file is refused.
The rest: `planned`, each pose as [x, y, z, qw, qx, qy, qz] in the robot file's world
frame; `recorded`, one {"pose": index into planned, "lengths": [m], "forces": [N]} per
pose flown (the averaged state at rest, tuning.calibration.Sample); `skipped`, one
{"pose": index, "reason": text} per pose the daemon refused to go to.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr import Pose
from cdpr.trusted_file import UnreadableFileError, read_trusted
from daemon.service.calibration_state import checksum, write_atomically
from tuning.calibration import Sample

if TYPE_CHECKING:
    from daemon.config import DaemonConfig

SCHEMA = 1
MAX_BYTES = 1 << 22  # a few thousand poses


class RoundFileError(RuntimeError):
    """The round file exists but cannot be used (names the file and the problem)."""


@dataclass
class CalibrationRound:
    """The poses planned, and what became of each so far (module docstring)."""

    robot: str
    identity: str
    offsets: list[float]
    planned: list[Pose]
    recorded: dict[int, Sample] = field(default_factory=dict)
    skipped: dict[int, str] = field(default_factory=dict)

    def remaining(self) -> list[int]:
        """The planned poses neither recorded nor skipped yet, in flying order."""
        done = self.recorded.keys() | self.skipped.keys()
        return [k for k in range(len(self.planned)) if k not in done]

    def samples(self) -> list[Sample]:
        """The samples recorded, in the planned order."""
        return [self.recorded[k] for k in sorted(self.recorded)]


def round_path(config: DaemonConfig) -> Path:
    """Where the round of `config`'s robot is kept: its state_dir, else beside the robot
    file (the config's directory when the robot is inline)."""
    name = f"{config.robot.name}.calibration-round.json"
    if config.state_dir is not None:
        return config.state_dir / name
    raw = config.raw.robot
    return (config.path(raw).parent if isinstance(raw, str) else config.base) / name


def save_round(path: Path, calibration_round: CalibrationRound) -> None:
    """Write `calibration_round` to `path` atomically; OSError if it cannot."""
    body: dict[str, Any] = {
        "schema": SCHEMA,
        "robot": calibration_round.robot,
        "identity": calibration_round.identity,
        "offsets": list(calibration_round.offsets),
        "planned": [
            [*map(float, p.position), *map(float, p.quaternion_tuple)]
            for p in calibration_round.planned
        ],
        "recorded": [
            {"pose": k, "lengths": s.lengths.tolist(), "forces": s.forces.tolist()}
            for k, s in sorted(calibration_round.recorded.items())
        ],
        "skipped": [
            {"pose": k, "reason": why} for k, why in sorted(calibration_round.skipped.items())
        ],
    }
    body["checksum"] = checksum(body)
    write_atomically(path, (json.dumps(body) + "\n").encode())


def load_round(path: Path, robot: str, n: int, identity: str) -> CalibrationRound | None:
    """The round in `path` (None: there is none), for robot `robot` with n cables and
    `identity` (robot_identity); RoundFileError names the file and what is wrong."""
    if not os.path.lexists(path):
        return None
    try:
        data = json.loads(read_trusted(path, MAX_BYTES).decode("utf-8"))
    except UnreadableFileError as exc:
        raise RoundFileError(str(exc)) from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise RoundFileError(f"{path}: corrupt (not JSON: {exc})") from None
    return _parse(data, path, robot, n, identity)


def _parse(data: Any, path: Path, robot: str, n: int, identity: str) -> CalibrationRound:
    def bad(key: str, problem: str) -> RoundFileError:
        return RoundFileError(f"{path}: {key}: {problem}")

    if not isinstance(data, dict):
        raise bad("(top)", f"expected an object, got {type(data).__name__}")
    if data.get("schema") != SCHEMA:
        raise bad("schema", f"expected {SCHEMA}, got {data.get('schema')!r}")
    try:
        expected = checksum({k: v for k, v in data.items() if k != "checksum"})
    except ValueError:  # a NaN or infinity: not what save_round writes
        expected = None
    if data.get("checksum") != expected:
        raise bad("checksum", "does not match the content (edited or damaged)")
    if data.get("robot") != robot:
        raise bad("robot", f"a round of robot {data.get('robot')!r}, not of {robot!r}")
    if data.get("identity") != identity:
        raise bad(
            "identity",
            "a round of another robot, or of this one before its robot file (anchors, "
            "attachments, pulleys, drums) or its drives changed",
        )
    offsets = _numbers(data.get("offsets"), n)
    if offsets is None:
        raise bad("offsets", f"expected {n} finite numbers (m), one per drive")
    rows = data.get("planned")
    if not isinstance(rows, list) or not rows:
        raise bad("planned", "expected a list of poses")
    planned = []
    for k, row in enumerate(rows):
        values = _numbers(row, 7) or []
        try:
            planned.append(Pose(values[:3], values[3:]))
        except ValueError:  # not 7 numbers, or not a unit quaternion
            raise bad(f"planned[{k}]", "expected [x, y, z, qw, qx, qy, qz]") from None
    seen: set[int] = set()

    def entries(key: str) -> list[tuple[str, dict[str, Any]]]:
        """Each entry of `key` (its name in messages, the entry), its pose checked."""
        value = data.get(key)
        if not isinstance(value, list):
            raise bad(key, "expected a list")
        out = []
        for i, entry in enumerate(value):
            where = f"{key}[{i}]"
            pose = entry.get("pose") if isinstance(entry, dict) else None
            if type(pose) is not int or not 0 <= pose < len(planned):
                raise bad(where, f"expected an object whose pose is one of the {len(planned)}")
            if pose in seen:
                raise bad(where, f"pose {pose} recorded or skipped twice")
            seen.add(pose)
            out.append((where, entry))
        return out

    recorded = {}
    for where, entry in entries("recorded"):
        lengths, forces = _numbers(entry.get("lengths"), n), _numbers(entry.get("forces"), n)
        if lengths is None or forces is None:
            raise bad(where, f"expected lengths and forces, {n} finite numbers each")
        recorded[entry["pose"]] = Sample(np.array(lengths), np.array(forces))
    skipped = {}
    for where, entry in entries("skipped"):
        if not isinstance(entry.get("reason"), str):
            raise bad(where, "expected a reason")
        skipped[entry["pose"]] = entry["reason"]
    return CalibrationRound(robot, identity, offsets, planned, recorded, skipped)


def _numbers(value: Any, n: int) -> list[float] | None:
    """`value` as n finite floats, or None."""
    if not (isinstance(value, list) and len(value) == n):
        return None
    if not all(type(x) in (int, float) and math.isfinite(x) for x in value):
        return None
    return [float(x) for x in value]
