"""Benchmark of path timing (cdpr.path.timing): how long planning takes, and how close
its durations come to an independent time-optimal bound.

    python bench/planning.py [--json] [--runs N] [--no-ratios]

- plan_ms.path_100: parse and time a 100-pose JSON path (a climbing square spiral,
  blended corners, 10 m) on config/reference8-cia402.yaml, median of N runs;
  plan_ms.gcode_2000: the same for a 2,000-line G-code file (a zig-zag, 1 cm blends);
  plan_ms.path_100_free: path_100 without a jerk limit (the config bounds the jerk).
  The allocator reuses freed large blocks and the objects of the start-up are frozen,
  as in the companion that times the daemon's paths (daemon.process.heap).
- duration_ratio.<path>: TOPP-RA's duration (1 cm grid) / the optimum of the convex
  formulation of tuning.convex_timing (Verscheure et al. 2009, tensions as variables,
  2 mm grid), both with a 5 N tension margin on reference8 without the winches' damping
  (which the convex form cannot hold): vertical_lift and edge_move (the standard
  trajectories' end poses, rest to rest), blended_corner (two sides of a square, 5 cm
  blend), without jerk limits (the convex form has none).  Within 3 % is the goal.
- Flown (--flown): the standard paths (figure_eight, vertical_lift, edge_move: the
  standard trajectories' poses without their times, corners blended 5 cm; gcode_200: a
  200-segment star part, 1 cm blends) timed as the daemon times a path (path_timer:
  reference8-cia402, its workspace margin) and flown in lock-step by the daemon's
  controller at 500 Hz on that config's simulated plant (the file's robot with 10 um
  encoder counts, 1 ms plant step: a robot calibrated to its file):
  tension_min_n.<path> / tension_max_n.<path> (the true tensions, against t_min and
  force_max in tension_range_n), tracking_rms_mm.<path> (true position against the
  reference), fault.<path> (empty when the controller never gave up), and
  speedup.<path>: the duration of the best constant-speed timing that the daemon's
  validation accepts (a trapezoid in path speed, or its ramps' acceleration a raised
  cosine: the fastest cruise found by bisection, for the best of six ramps) over the
  planned one.
- --free-jerk: the flown paths timed (and validated) without the config's jerk limits.
- Jerk (--jerk): the standard paths above timed by time_path on reference8-cia402 as its
  file sets the trajectory limits, and again with the jerk bounded (JERK: the config's
  linear_jerk / angular_jerk where it sets them, else these): jerk_peak.<path> the largest
  linear and angular jerk (m/s³, rad/s³, cdpr.trajectory.jerk) without and with the
  bound, jerk_cost.<path> the bounded duration over the unbounded one.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import time

import numpy as np
from timing import REFERENCE8

from cdpr.controller import ParallelController
from cdpr.path import Path, PathPoint, parse_gcode, parse_path
from cdpr.path.geometry import BlendedPath
from cdpr.path.timing import Timing, time_path
from cdpr.pose import Pose
from cdpr.so3 import quat_from_matrix
from cdpr.trajectory import Trajectory, TrajectoryError, TrajectoryLimits
from cdpr.trajectory.jerk import segment_jerks
from cdpr.wrench_margin import wrench_length
from daemon.cli.simulated import sim_section
from daemon.config import load_config
from daemon.process.heap import freeze_start_up, reuse_freed_memory
from daemon.service.planner import path_timer, validate_as_the_daemon
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking

CONFIG = REFERENCE8.parent.parent / "reference8-cia402.yaml"
MARGIN = 5.0
JERK = {"linear_jerk": 50.0, "angular_jerk": 100.0}  # m/s³, rad/s³ where the config sets none


def spiral(n: int) -> dict:
    q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    poses = [{"position": [0.0, 0.0, 1.0], "quaternion": q}]
    for k in range(1, n):
        x, y = 0.25 * ((k % 4) in (1, 2)), 0.25 * ((k % 4) >= 2)
        poses.append({"position": [x, y, 1.0 + 0.005 * k], "blend": 0.03})
    return {"poses": poses}


def zigzag(lines: int) -> str:
    rows = ["G21 G90 F30000"]
    rows += [f"G1 X{100 * (k % 2)} Y{-100 + 0.1 * k:.1f}" for k in range(lines - 1)]
    return "\n".join(rows)


def jerk_bounded(limits: TrajectoryLimits) -> TrajectoryLimits:
    """`limits` with the jerk bounded: JERK where they set no jerk limit."""
    return limits.model_copy(update={k: getattr(limits, k) or v for k, v in JERK.items()})


def jerk_free(limits: TrajectoryLimits) -> TrajectoryLimits:
    """`limits` without jerk limits."""
    return limits.model_copy(update=dict.fromkeys(JERK))


def plan_ms(config, runs: int) -> dict[str, float]:
    reuse_freed_memory()
    freeze_start_up()
    robot, limits = config.robot, config.trajectory
    free = jerk_free(limits)
    body, program = spiral(100), zigzag(2000)
    out = {}
    for name, make, timed_within in (
        ("path_100", lambda: parse_path(body, limits), limits),
        ("gcode_2000", lambda: parse_gcode(program, robot.home, 0.01, limits), limits),
        ("path_100_free", lambda: parse_path(body, free), free),
    ):
        times = []
        for _ in range(runs):
            began = time.perf_counter()
            time_path(make(), robot, timed_within, Timing(margin=MARGIN))
            times.append(time.perf_counter() - began)
        out[name] = round(1e3 * float(np.median(times)), 1)
    return out


def duration_ratios(config) -> dict[str, float]:
    from tuning.convex_timing import convex_duration

    robot = copy.deepcopy(config.robot)
    robot.k0 = np.zeros_like(robot.k0)
    limits, home = jerk_free(config.trajectory), robot.home

    def at(dx: float, dy: float, dz: float, turn: float = 0.0) -> Pose:
        return Pose.from_rotvec(home.position + np.array([dx, dy, dz]), [0.0, 0.0, turn])

    cases = {
        "vertical_lift": [at(0, 0, -0.5), at(0, 0, 0.5)],
        "edge_move": [at(-0.6, 0.55, -0.35, -0.15), at(0.6, 0.55, -0.35, 0.15)],
        "blended_corner": [at(0, 0, 0), at(0.3, 0, 0), at(0.3, 0.3, 0.1)],
    }
    out = {}
    for name, poses in cases.items():
        blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
        path = Path(tuple(PathPoint(p, blend=r) for p, r in zip(poses, blends, strict=True)))
        planned = time_path(path, robot, limits, Timing(margin=MARGIN)).duration
        optimum = convex_duration(poses, blends, robot, limits, MARGIN, step=0.002)
        out[name] = round(planned / optimum, 4)
    return out


def standard_paths(config) -> dict[str, Path]:
    """The flown paths (module docstring)."""
    robot = config.robot
    paths = {}
    for name in ("figure_eight", "vertical_lift", "edge_move"):
        poses = [w.pose for w in STANDARD_SET[name](robot).waypoints]
        blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
        paths[name] = Path(tuple(PathPoint(p, blend=b) for p, b in zip(poses, blends, strict=True)))
    paths["gcode_200"] = parse_gcode(star(200), robot.home, 0.01, config.trajectory)
    return paths


def star(segments: int) -> str:
    """A G-code star about home: `segments` moves between radii 150 and 80 mm."""
    rows = ["G21 G91 F30000", "G1 X150 Y0"]
    point = np.array([150.0, 0.0])
    for k in range(1, segments):
        radius = 150.0 if k % 2 == 0 else 80.0
        angle = 2.0 * np.pi * k / 20.0
        target = radius * np.array([np.cos(angle), np.sin(angle)])
        dx, dy = target - point
        rows.append(f"G1 X{dx:.3f} Y{dy:.3f}")
        point = target
    return "\n".join(rows)


def constant_speed(
    path: Path, length: float, speed: float, accel: float, smooth: bool = False
) -> Trajectory:
    """`path` (one motion) flown at path speed `speed` (m/s of path), reached and left
    at path acceleration `accel`: at once (a trapezoid in path speed) or, `smooth`, along
    a raised cosine peaking at `accel` (no step in acceleration: a path jerk of at most
    pi accel^2 / (2 speed)); sampled in time, 1 cm of path apart at most."""
    geometry = BlendedPath([p.pose for p in path.points], [p.blend for p in path.points], length)
    total = geometry.s_end
    # the ramp's share of the speed's square it takes in path, then its duration
    reach = 1.0 if smooth else 0.5
    speed = min(speed, float(np.sqrt(accel * total / (2.0 * reach))))  # never cruises
    ramp_t = (2.0 if smooth else 1.0) * speed / accel
    ramp_s = reach * speed**2 / accel
    end = 2.0 * ramp_t + (total - 2.0 * ramp_s) / speed
    t = np.linspace(0.0, end, max(int(np.ceil(end * speed / 0.01)), 2) + 1)

    def up(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, s', s'') on the ramp up, tau s into it."""
        if not smooth:
            return 0.5 * accel * tau**2, accel * tau, np.full_like(tau, accel)
        w = 2.0 * np.pi / ramp_t
        k = speed / ramp_t
        return (
            k * (0.5 * tau**2 - (1.0 - np.cos(w * tau)) / w**2),
            k * (tau - np.sin(w * tau) / w),
            k * (1.0 - np.cos(w * tau)),
        )

    rising, falling = up(np.minimum(t, ramp_t)), up(np.clip(end - t, 0.0, ramp_t))
    cruise = ramp_s + speed * (t - ramp_t)
    s = np.where(t <= ramp_t, rising[0], np.where(t < end - ramp_t, cruise, total - falling[0]))
    sd = np.where(t <= ramp_t, rising[1], np.where(t < end - ramp_t, speed, falling[1]))
    sdd = np.where(t <= ramp_t, rising[2], np.where(t < end - ramp_t, 0.0, -falling[2]))
    positions, rotations, p1, w1, p2, w2 = geometry.poses(np.clip(s, 0.0, total))
    v, a = np.hstack([p1, w1]), np.hstack([p2, w2])
    twists, accels = v * sd[:, None], v * sdd[:, None] + a * (sd**2)[:, None]
    twists[[0, -1]] = accels[[0, -1]] = 0.0
    return Trajectory.through(t, positions, quat_from_matrix(rotations), twists, accels)


def best_constant_speed(path: Path, config) -> float:
    """The shortest duration of a constant-speed timing of `path` that the daemon's
    validation accepts (module docstring)."""
    length = wrench_length(config.robot.geometry.attachments)
    best = np.inf
    for share, smooth in itertools.product((0.25, 0.5, 1.0), (False, True)):
        accel = share * config.trajectory.linear_accel
        lo, hi = 0.0, 2.0 * config.trajectory.linear_speed
        for _ in range(14):
            mid = 0.5 * (lo + hi)
            try:
                validate_as_the_daemon(constant_speed(path, length, mid, accel, smooth), config)
                lo = mid
            except TrajectoryError:
                hi = mid
        if lo > 0.0:
            best = min(best, constant_speed(path, length, lo, accel, smooth).duration)
    return best


def flown(config) -> dict[str, dict]:
    """The flown keys (module docstring)."""
    robot, spec = config.robot, config.controller
    plant = sim_section(config).plant
    timer = path_timer(config)
    out: dict[str, dict] = {
        k: {} for k in ("tension_min_n", "tension_max_n", "tracking_rms_mm", "fault", "speedup")
    }
    out["tension_range_n"] = {
        "t_min": float(min(robot.t_min)),
        "force_max": float(min(robot.force_max)),
    }
    for name, path in standard_paths(config).items():
        trajectory = timer(path)
        validate_as_the_daemon(trajectory, config)
        run = run_tracking(robot, trajectory, ParallelController(robot, spec), plant, spec.rate_hz)
        out["tension_min_n"][name] = round(run.min_tension, 2)
        out["tension_max_n"][name] = round(run.max_tension, 2)
        out["tracking_rms_mm"][name] = round(run.rms_mm, 4)
        out["fault"][name] = run.fault
        out["speedup"][name] = round(best_constant_speed(path, config) / trajectory.duration, 3)
    return out


def jerk_figures(config) -> dict[str, dict]:
    """The jerk keys (module docstring)."""
    free, bound = jerk_free(config.trajectory), jerk_bounded(config.trajectory)
    out: dict[str, dict] = {"jerk_peak": {}, "jerk_cost": {}}
    out["jerk_limits"] = {k: getattr(bound, k) for k in JERK}
    for name, path in standard_paths(config).items():
        timed = [time_path(path, config.robot, limits, Timing(MARGIN)) for limits in (free, bound)]
        peaks = [segment_jerks(*t.curve.segments()[1:]) for t in timed]
        out["jerk_peak"][name] = {
            which: [round(float(p.max()), 1) for p in peak]
            for which, peak in zip(("free", "bound"), peaks, strict=True)
        }
        out["jerk_cost"][name] = round(timed[1].duration / timed[0].duration, 3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--no-ratios", action="store_true", help="skip the convex bounds")
    parser.add_argument("--flown", action="store_true", help="fly the standard paths too")
    parser.add_argument("--jerk", action="store_true", help="the jerk figures too")
    parser.add_argument(
        "--free-jerk", action="store_true", help="fly the paths timed without jerk limits"
    )
    args = parser.parse_args()
    config = load_config(CONFIG)
    if args.free_jerk:
        config.trajectory = jerk_free(config.trajectory)
    result = {"plan_ms": plan_ms(config, args.runs)}
    if not args.no_ratios:
        result["duration_ratio"] = duration_ratios(config)
    if args.flown:
        result.update(flown(config))
    if args.jerk:
        result.update(jerk_figures(config))
    if args.json:
        print(json.dumps(result))
    else:
        for group, values in result.items():
            for key, value in values.items():
                print(f"{group}.{key}: {value}")


if __name__ == "__main__":
    main()
