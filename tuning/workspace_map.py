"""The robot's workspace on a grid (`cdprd workspace`): where the platform can be, at a
set of orientations and over a payload range, and by how much.

A grid point at an orientation is in the workspace when, there,
- the platform's body lies inside the workspace box and clear of the environment, and the
  cables clear of its obstacles (cdpr.body, the runtime monitor's checks without margins);
- every cable length lies within its [length_min, length_max];
- no two cables come closer than their diameters and no cable runs through the body
  (cdpr.interference);
- the wrench that holds the platform at rest, with any payload of the range (at its
  centre of mass), lies inside the wrenches the tensions [t_min, force_max] give, by at
  least the required margin (cdpr.wrench_margin; the margin is concave along the payload
  range, so its two ends bound it).

Each point keeps its capacity margin (N) or the first reason it is out, in a
cdpr.workspace_map.WorkspaceMap (its file, summary and fingerprint).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from cdpr.body import Environment, segments_meet
from cdpr.compiled_cache import key_numba_cache
from cdpr.interference import touch_kernel
from cdpr.robot import Robot
from cdpr.so3 import quat_multiply, quat_to_matrix
from cdpr.workspace_check import WorkspaceCheck, place
from cdpr.workspace_map import (
    BOX,
    ENVIRONMENT,
    IN,
    INTERFERENCE,
    LENGTH,
    MapSettings,
    WorkspaceMap,
    fingerprint,
)
from cdpr.wrench_margin import margin_kernel, margin_scratch, rest_wrenches

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

_CHUNK = 65536  # grid points per batch: a few MB of arrays


def orientations(home: Sequence[float], tilt: float) -> Array:
    """Home and the 8 orientations tilted by `tilt` (rad) about the horizontal axes at
    45 degree steps (unit quaternions w, x, y, z, one per row)."""
    rows = [np.asarray(home, dtype=float)]
    if tilt > 0.0:
        for i in range(8):
            a = i * math.pi / 4.0
            axis = np.array([math.cos(a), math.sin(a), 0.0])
            tilt_q = np.concatenate([[math.cos(tilt / 2.0)], math.sin(tilt / 2.0) * axis])
            rows.append(quat_multiply(tilt_q, home))
    return np.array(rows)


def compute_map(
    robot: Robot,
    lower: Sequence[float],
    upper: Sequence[float],
    environment: Environment,
    settings: MapSettings,
) -> WorkspaceMap:
    """The workspace map of `robot` in the box [lower, upper] (m)."""
    start = time.perf_counter()
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    step = settings.step
    shape = tuple(math.floor(span / step + 1e-9) + 1 for span in (hi - lo).tolist())
    quats = orientations(robot.home.quaternion_tuple, settings.tilt)
    margin = np.full((len(quats), *shape), np.nan, np.float32)
    reason = np.zeros((len(quats), *shape), np.int8)
    axes = [lo[a] + step * np.arange(n) for a, n in enumerate(shape)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    check = WorkspaceCheck.of(robot)
    for o, q in enumerate(quats):
        R = quat_to_matrix(q)
        flat_margin = margin[o].reshape(-1)
        flat_reason = reason[o].reshape(-1)
        for begin in range(0, len(grid), _CHUNK):
            span = slice(begin, begin + _CHUNK)
            flat_reason[span], flat_margin[span] = _classify(
                check, grid[span], R, lo, hi, environment, settings
            )
    return WorkspaceMap(
        lo,
        step,
        quats,
        margin,
        reason,
        settings,
        fingerprint(robot, lo, hi, environment, settings),
        time.perf_counter() - start,
    )


def _classify(
    check: WorkspaceCheck,
    P: Array,
    R: Array,
    lo: Array,
    hi: Array,
    environment: Environment,
    settings: MapSettings,
) -> tuple[NDArray[np.int8], NDArray[np.float32]]:
    """Reason codes and margins of positions P at rotation R: the body in the box and
    clear of the environment here (numpy, whole arrays), the rest per point in one
    compiled pass (_cables)."""
    robot = check.robot
    reason = np.full(len(P), IN, np.int8)
    margin = np.full(len(P), np.nan, np.float32)
    corners = robot.body.points.dot(R.T)
    in_box = np.all(P + corners.min(axis=0) >= lo, axis=1) & np.all(
        P + corners.max(axis=0) <= hi, axis=1
    )
    reason[~in_box] = BOX
    left = np.flatnonzero(in_box)
    clear = _clear(robot, P[left], R, corners, environment)
    reason[left[~clear]] = ENVIRONMENT
    left = left[clear]
    wrenches, touches = check.wrenches, check.touches
    com = robot.platform.center_of_mass  # payloads sit at the platform's centre of mass
    payloads = sorted(set(settings.payload))
    needed = np.array([rest_wrenches(robot.platform, R[None], m, com)[0] for m in payloads])
    if any(pulley is not None for pulley in robot.geometry.pulleys):
        placed = place(robot, P[left], R)  # the pulleys' leave points, in numpy
        lengths, u, starts = placed.lengths, placed.jacobians[:, :, :3], placed.starts
    else:  # straight cables: computed point by point in the pass
        lengths, u = np.zeros((0, robot.n_cables)), np.zeros((0, robot.n_cables, 3))
        starts = u
    codes, margins = np.empty(len(left), np.int8), np.empty(len(left), np.float32)
    geometry = robot.geometry
    pairs, gaps, faces, on_face = touches.pairs, touches.gaps, touches.faces, touches.on_face
    if not settings.interference:  # no pair to compare, no face to leave
        pairs, gaps, faces = pairs[:0], gaps[:0], faces[:0]
        on_face = np.ascontiguousarray(on_face[:, :0])
    _cables(
        np.ascontiguousarray(P[left]), R, geometry.anchors, geometry.attachments.dot(R.T),
        robot.length_min, robot.length_max, np.ascontiguousarray(lengths),
        np.ascontiguousarray(u), np.ascontiguousarray(starts),
        pairs, gaps, faces, on_face,
        wrenches.scale, needed, wrenches.t_lo, wrenches.t_hi, wrenches.combos, codes, margins,
    )  # fmt: skip
    reason[left] = codes
    margin[left] = margins
    return reason, margin


@njit(cache=True, parallel=True)
def _cables(
    P: Array,
    R: Array,
    anchors: Array,
    offsets: Array,
    length_min: Array,
    length_max: Array,
    lengths: Array,
    directions: Array,
    starts: Array,
    pairs: NDArray[np.int64],
    gaps: Array,
    faces: Array,
    on_face: NDArray[np.bool_],
    scale: Array,
    needed: Array,
    t_lo: Array,
    t_hi: Array,
    combos: NDArray[np.int64],
    codes: NDArray[np.int8],
    margins: NDArray[np.float32],
) -> None:
    """Per position P[p] at rotation R (the cables' attachments at P[p] + offsets): the
    cable lengths in their ranges (else LENGTH), no interference (else INTERFERENCE), and
    the smallest capacity margin of the `needed` rest wrenches (IN, margins[p]).  With
    `lengths`, `directions` and `starts` given (pulleys: one row per position) they are
    read; empty, each cable runs straight from its anchor.  In chunks on every core."""
    count, n = P.shape[0], anchors.shape[0]
    straight = lengths.shape[0] == 0
    chunks = min(count, 64)
    for c in prange(chunks):
        work = margin_scratch(6, n)
        v = np.empty(combos.shape[1])
        A = np.empty((6, n))
        w = np.empty(6)
        ends = np.empty((n, 3))
        for p in range(c * count // chunks, (c + 1) * count // chunks):
            codes[p] = IN
            for k in range(n):
                for i in range(3):
                    ends[k, i] = P[p, i] + offsets[k, i]
                if straight:
                    dx = ends[k, 0] - anchors[k, 0]
                    dy = ends[k, 1] - anchors[k, 1]
                    dz = ends[k, 2] - anchors[k, 2]
                    length = math.sqrt(dx * dx + dy * dy + dz * dz)
                    ux, uy, uz = dx / length, dy / length, dz / length
                else:
                    length = lengths[p, k]
                    ux, uy, uz = directions[p, k, 0], directions[p, k, 1], directions[p, k, 2]
                if not length_min[k] <= length <= length_max[k]:
                    codes[p] = LENGTH
                    break
                rx, ry, rz = offsets[k, 0], offsets[k, 1], offsets[k, 2]
                A[0, k], A[1, k], A[2, k] = ux, uy, uz
                A[3, k] = (ry * uz - rz * uy) * scale[3]
                A[4, k] = (rz * ux - rx * uz) * scale[4]
                A[5, k] = (rx * uy - ry * ux) * scale[5]
            if codes[p] != IN:
                continue
            origins = anchors if straight else starts[p]
            if touch_kernel(origins, ends, R, pairs, gaps, faces, on_face)[0] >= 0:
                codes[p] = INTERFERENCE
                continue
            best = np.inf
            for j in range(needed.shape[0]):
                for i in range(6):
                    w[i] = needed[j, i] * scale[i]
                best = min(best, margin_kernel(A, w, t_lo, t_hi, combos, v, work)[0])
            margins[p] = best


def _clear(
    robot: Robot, P: Array, R: Array, corners: Array, environment: Environment
) -> NDArray[np.bool_]:
    """Per position: the body clear of every plane and box, the cables of every box."""
    clear = np.ones(len(P), np.bool_)
    for plane in environment.planes:
        n = np.asarray(plane.normal)
        clear &= P.dot(n) + corners.dot(n).min() >= plane.offset
    if not environment.boxes:
        return clear
    world = P[:, None, :] + corners
    attached = world[:, list(robot.body.attachment_of), :]
    anchors = robot.geometry.anchors
    for box in environment.boxes:
        clear &= ~robot.body.meets_many(world, R, box, 0.0)
        for k in range(robot.n_cables):
            starts = np.broadcast_to(anchors[k], (len(P), 3))
            clear &= ~segments_meet(
                starts, attached[:, k], np.array(box.lower), np.array(box.upper)
            )
    return clear


def plot_slices(workspace: WorkspaceMap, path: str | Path, title: str) -> None:
    """A PNG of the workspace at home: horizontal slices at a quarter, half and three
    quarters of the box's height and the vertical slice through its middle in y, each
    point coloured by its margin (N), grey where it is out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nx, ny, nz = workspace.shape
    margin = np.where(workspace.inside()[0], workspace.margin[0], np.nan)
    x0, y0, z0 = workspace.origin
    s = workspace.step
    extent_xy = (x0, x0 + s * (nx - 1), y0, y0 + s * (ny - 1))
    top = np.nanmax(margin) if np.isfinite(margin).any() else 1.0
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.8), constrained_layout=True)
    image = None
    for ax, fraction in zip(axes[:3], (0.25, 0.5, 0.75), strict=True):
        k = round(fraction * (nz - 1))
        ax.set_facecolor("0.85")
        image = ax.imshow(
            margin[:, :, k].T, origin="lower", extent=extent_xy, vmin=0.0, vmax=top, cmap="viridis"
        )
        ax.set(title=f"z = {z0 + s * k:.2f} m", xlabel="x (m)", ylabel="y (m)", aspect="equal")
    j = (ny - 1) // 2
    ax = axes[3]
    ax.set_facecolor("0.85")
    ax.imshow(
        margin[:, j, :].T,
        origin="lower",
        extent=(x0, x0 + s * (nx - 1), z0, z0 + s * (nz - 1)),
        vmin=0.0,
        vmax=top,
        cmap="viridis",
    )
    ax.set(title=f"y = {y0 + s * j:.2f} m", xlabel="x (m)", ylabel="z (m)", aspect="equal")
    fig.colorbar(image, ax=axes, label="capacity margin (N); grey: out of the workspace")
    fig.suptitle(title)
    fig.savefig(path, dpi=80)
    plt.close(fig)
