"""Paths: poses without times, timed by cdprd within the cables' tensions (issue: path
timing).  `parse_path` reads the JSON form, `parse_gcode` G-code; `time_path` turns a
Path into a Trajectory the daemon validates and flies like a client's."""

from cdpr.path.gcode import parse_gcode
from cdpr.path.model import Path, PathPoint
from cdpr.path.parse import parse_path

__all__ = ["Path", "PathPoint", "parse_gcode", "parse_path"]
