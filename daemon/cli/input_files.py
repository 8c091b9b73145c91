"""The files the command-line tools read: a request (a trajectory, a path, a zenoh
config) as a YAML or JSON mapping, and a path from its JSON/YAML form or from G-code.
Both `cdprd send` and `cdprd plan` read paths here, so that one file means one path."""

from __future__ import annotations

import json
import math
from pathlib import Path as FilePath
from typing import TYPE_CHECKING, Any

from cdpr.description import ConfigError, load_yaml, read_text
from cdpr.path import Path, parse_gcode, parse_path
from cdpr.trajectory import TrajectoryLimits

if TYPE_CHECKING:
    from daemon.config import DaemonConfig

REQUEST_FILE_MAX_BYTES = 64 << 20  # a trajectory file (the daemon limits what it takes)
GCODE = (".gcode", ".gc", ".nc", ".ngc")


class UsageError(Exception):
    """A bad argument or input file (exit 2)."""


def read_mapping(path: str) -> dict[str, Any]:
    """A YAML or JSON file (a regular file of at most REQUEST_FILE_MAX_BYTES) holding a
    mapping of strict-JSON values."""
    file = FilePath(path)
    try:
        if file.suffix.lower() == ".json":
            data = json.loads(read_text(file, REQUEST_FILE_MAX_BYTES))
        else:
            data = load_yaml(file, REQUEST_FILE_MAX_BYTES)
        json.dumps(data, allow_nan=False)
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:  # bad JSON, NaN / Infinity
        raise UsageError(f"{path}: not strict JSON data: {exc}") from None
    if not isinstance(data, dict):
        raise UsageError(f"{path}: expected a mapping, got {type(data).__name__}")
    return data


def read_path(
    file: str, config: DaemonConfig | None, blend: float, gcode: bool | None = None
) -> Path:
    """The path in `file`: G-code (`gcode`; None: by its suffix, GCODE) from `config`'s
    robot home, each corner rounded by `blend` m, else a path's JSON or YAML form (within
    `config`'s trajectory limits, the defaults without one).  UsageError for an unreadable
    file or a bad blend, TrajectoryError naming the pose or line."""
    limits = TrajectoryLimits() if config is None else config.trajectory
    if gcode is None:
        gcode = FilePath(file).suffix.lower() in GCODE
    if gcode:
        assert config is not None, "G-code starts at a config's robot home"
        if not (math.isfinite(blend) and blend >= 0.0):
            raise UsageError(f"--blend: {blend:g} must be a number >= 0")
        try:
            text = read_text(FilePath(file), REQUEST_FILE_MAX_BYTES)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
        return parse_gcode(text, config.robot.home, blend, limits)
    return parse_path(read_mapping(file), limits)


