"""Benchmark of the workspace: its correctness against independent references, the map's
speed and the daemon's per-sample check.

    python bench/workspace.py [--json] [--poses N] [--step M] [--config FILE]

- lp_agreement: on N random poses of reference8 (default 10,000: positions in the
  anchors' box, tilts up to 0.4 rad, payloads 0-8 kg), the share whose capacity-margin
  verdict (cdpr.wrench_margin: inside W or not) is the one scipy's HiGHS LP gives for
  "W t = w, t_min <= t <= force_max", over the poses farther than 0.5 N from the boundary
  (`lp_compared`, `lp_feasible` of them in W).
- interference_agreement: on the same poses, the share whose interference verdict
  (cdpr.interference) is brute force's: each pair's distance by a ternary search of the
  point-to-segment distance along one cable, each cable against the body by 400 points
  along it tested against the hull's facets (scipy's ConvexHull); poses within 1e-6 m of
  a diameter are left out (`interference_compared`, `interference_found`).
- seconds, points_per_second: the map of config/reference8-cia402.yaml at `--step`
  (default 0.02 m) x 9 orientations (tuning.workspace_map) with the config's settings
  (reference8's: no interference check, its crossed pairs being idealised), the volume
  and worst margin.
- per_sample_us: the daemon's check (cdpr.workspace_check.WorkspaceCheck.first_refusal)
  with the interference check on (the default), on CHUNK samples at once, as validation
  runs it (cdpr.trajectory.limits.CHUNK), per sample (median of up to 50 batches).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull
from timing import REFERENCE8

from cdpr import Robot
from cdpr.so3 import quat_to_matrix
from cdpr.trajectory.limits import CHUNK
from cdpr.workspace_check import WorkspaceCheck, place
from cdpr.wrench_margin import rest_wrenches
from daemon.config import load_config
from tuning.workspace_map import compute_map

SURE = 0.5  # N from the boundary: the LP's verdict is compared beyond it


def random_poses(robot: Robot, count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (in the anchors' box less 0.3 m), rotations (up to 0.4 rad from home)
    and payloads (0-8 kg)."""
    rng = np.random.default_rng(seed)
    anchors = robot.geometry.anchors
    positions = rng.uniform(anchors.min(axis=0) + 0.3, anchors.max(axis=0) - 0.3, (count, 3))
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0.0, 0.4, count)
    quats = np.column_stack([np.cos(angles / 2), np.sin(angles / 2)[:, None] * axes])
    rotations = np.array([quat_to_matrix(q) for q in quats])
    return positions, rotations, rng.uniform(0.0, 8.0, count)


def lp_agreement(robot: Robot, check: WorkspaceCheck, poses: tuple) -> dict[str, float]:
    positions, rotations, payloads = poses
    placed = place(robot, positions, rotations)
    wrenches = np.array(
        [
            rest_wrenches(robot.platform, R[None], m)[0]
            for R, m in zip(rotations, payloads, strict=True)
        ]
    )
    margins = check.wrenches.margins(placed.jacobians, wrenches)
    bounds = list(zip(robot.t_min, robot.force_max, strict=True))
    compared = agree = feasible = 0
    for J, w, margin in zip(placed.jacobians, wrenches, margins, strict=True):
        if abs(margin) <= SURE:
            continue
        result = linprog(np.zeros(len(bounds)), A_eq=J.T, b_eq=w, bounds=bounds, method="highs")
        inside = result.status == 0
        compared += 1
        feasible += inside
        agree += inside == (margin > 0.0)
    return {"lp_agreement": agree / compared, "lp_compared": compared, "lp_feasible": feasible}


def _point_segment(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points x (..., 3) from segments a-b (..., 3)."""
    d = b - a
    s = np.clip(np.sum((x - a) * d, axis=-1) / np.sum(d * d, axis=-1), 0.0, 1.0)
    return np.linalg.norm(x - (a + s[..., None] * d), axis=-1)


def brute_pair_distances(p1, q1, p2, q2) -> np.ndarray:
    """Segment distances (vectorised over the leading axes) by ternary search along
    segment 1 of the distance to segment 2 (convex in the parameter)."""
    lo, hi = np.zeros(p1.shape[:-1]), np.ones(p1.shape[:-1])
    for _ in range(100):
        a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        fa = _point_segment(p1 + a[..., None] * (q1 - p1), p2, q2)
        fb = _point_segment(p1 + b[..., None] * (q1 - p1), p2, q2)
        lo, hi = np.where(fa < fb, lo, a), np.where(fa < fb, b, hi)
    return _point_segment(p1 + lo[..., None] * (q1 - p1), p2, q2)


def interference_agreement(robot: Robot, check: WorkspaceCheck, poses: tuple) -> dict:
    positions, rotations, _ = poses
    placed = place(robot, positions, rotations)
    found = check.touches.any(placed.starts, placed.ends, placed.rotations)
    g = robot.geometry
    n = robot.n_cables
    pairs = [
        (i, j)
        for i in range(n)
        for j in range(i + 1, n)
        if not (
            np.array_equal(g.anchors[i], g.anchors[j])
            or np.array_equal(g.attachments[i], g.attachments[j])
        )
    ]
    first, second = np.array(pairs).T
    s, e = placed.starts, placed.ends
    distances = brute_pair_distances(s[:, first], e[:, first], s[:, second], e[:, second])
    gaps = 0.5 * (robot.cable_diameter[first] + robot.cable_diameter[second])
    touching = distances < gaps
    near = np.abs(distances - gaps) < 1e-6
    hull = ConvexHull(robot.body.points)
    steps = np.linspace(1e-3, 1.0, 400)
    through = np.zeros(len(positions), np.bool_)
    for k in range(n):
        world = e[:, k, None, :] + steps[None, :, None] * (s[:, k] - e[:, k])[:, None, :]
        local = np.einsum("nji,nsj->nsi", rotations, world - positions[:, None, :])
        inside = np.all(local @ hull.equations[:, :3].T + hull.equations[:, 3] < -1e-9, axis=-1)
        through |= inside.any(axis=1)
    brute = touching.any(axis=1) | through
    kept = ~near.any(axis=1)
    return {
        "interference_agreement": float(np.mean(found[kept] == brute[kept])),
        "interference_compared": int(kept.sum()),
        "interference_found": int(brute[kept].sum()),
    }


def per_sample_us(robot: Robot, check: WorkspaceCheck, poses: tuple) -> float:
    positions, rotations, _ = poses
    check.first_refusal(positions[:CHUNK], rotations[:CHUNK])  # compiled or loaded
    times = []
    for b in range(min(50, len(positions) // CHUNK)):
        span = slice(CHUNK * b, CHUNK * (b + 1))
        start = time.perf_counter()
        check.first_refusal(positions[span], rotations[span])
        times.append((time.perf_counter() - start) / CHUNK)
    return float(np.median(times) * 1e6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--poses", type=int, default=10_000)
    parser.add_argument("--step", type=float, default=0.02)
    parser.add_argument(
        "--config", default=str(REFERENCE8.parent.parent / "reference8-cia402.yaml")
    )
    args = parser.parse_args()
    config = load_config(args.config)
    robot = config.robot
    check = config.workspace_check
    poses = random_poses(robot, args.poses, seed=1)
    out: dict = {"poses": args.poses}
    out.update(lp_agreement(robot, check, poses))
    out.update(interference_agreement(robot, check, poses))
    checking = WorkspaceCheck.of(robot, config.workspace.margin, interference=True)
    out["per_sample_us"] = round(per_sample_us(robot, checking, random_poses(robot, 6400, 2)), 2)
    lower, upper = config.workspace_box
    settings = config.workspace.map_settings(config.safety.tilt_max, step=args.step)
    summary = compute_map(robot, lower, upper, config.environment, settings).summary()
    out.update(
        {
            "step": args.step,
            "seconds": summary["seconds"],
            "points": summary["points"],
            "points_per_second": summary["points_per_second"],
            "volume_home_m3": summary["volume_per_orientation_m3"][0],
            "worst_margin_n": summary["worst_margin_n"],
        }
    )
    if args.json:
        print(json.dumps(out))
    else:
        for key, value in out.items():
            print(f"{key:>24}: {value}")


if __name__ == "__main__":
    main()
