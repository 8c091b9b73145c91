"""A 3-D picture of the robot without Foxglove: frame, cables coloured by tension,
platform and path, drawn with matplotlib (Agg, no display), for `cdprd demo --plot` and
`cdprd analyze --plot`."""

from __future__ import annotations

from itertools import combinations, product
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from cdpr import Pose, Robot

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: the style of a slack cable (tension <= 0 or below the robot's t_min)
SLACK_COLOR = "0.6"
SLACK_STYLE = "--"
#: the colormap of taut cables' tensions (N)
TENSION_CMAP = "viridis"


def draw_robot_3d(
    robot: Robot,
    pose: Pose,
    tensions: ArrayLike,
    *,
    path: ArrayLike | None = None,
    reference: ArrayLike | None = None,
    title: str | None = None,
) -> Figure:
    """A matplotlib Figure of `robot` at `pose`: anchors and their bounding box (thin
    lines), one line per cable from its anchor to its attachment point coloured by its
    tension (colorbar in N; slack cables grey and dashed), the platform as the box
    through its attachment points (in platform coordinates, so it turns with the
    platform), and the platform's `path` and `reference` path (n x 3 positions).

    A cable is drawn as the straight segment anchor -> attachment point, also for a
    robot with pulleys (the wrap round the pulley is not drawn).  Artists carry gids:
    "cable-k", "frame", "platform", "path", "reference"."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    t = np.asarray(tensions, dtype=float)
    if t.shape != (robot.n_cables,):
        raise ValueError(f"expected {robot.n_cables} tensions, got shape {t.shape}")
    anchors = robot.geometry.anchors
    points = pose.position + robot.geometry.attachments @ pose.rotation.T
    slack = robot.slack(t)

    fig = Figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    lo, hi = anchors.min(axis=0), anchors.max(axis=0)
    for a, b in _box_edges(lo, hi):
        ax.plot(*np.transpose([a, b]), color="0.3", lw=0.6, gid="frame")
    ax.scatter(*anchors.T, color="k", s=15, depthshade=False, gid="anchors")

    taut = t[~slack]
    norm = Normalize(*((taut.min(), taut.max()) if taut.size else (0.0, 1.0)))
    if norm.vmin == norm.vmax:
        norm = Normalize(norm.vmin - 1.0, norm.vmax + 1.0)
    cmap = colormaps[TENSION_CMAP]
    for k, (a, b) in enumerate(zip(anchors, points, strict=True)):
        style = (
            {"color": SLACK_COLOR, "linestyle": SLACK_STYLE}
            if slack[k]
            else {"color": cmap(norm(t[k])), "linestyle": "-"}
        )
        ax.plot(*np.transpose([a, b]), lw=2.0, gid=f"cable-{k}", **style)
    fig.colorbar(ScalarMappable(norm, cmap), ax=ax, shrink=0.6, label="cable tension (N)")

    body = robot.geometry.attachments
    blo, bhi = body.min(axis=0), body.max(axis=0)
    corners = {
        c: pose.position + pose.rotation @ np.choose(c, [blo, bhi])
        for c in product((0, 1), repeat=3)
    }
    faces = [
        [corners[c] for c in ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0))],
        [corners[c] for c in ((0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))],
        [corners[c] for c in ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1))],
        [corners[c] for c in ((0, 1, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1))],
        [corners[c] for c in ((0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1))],
        [corners[c] for c in ((1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1))],
    ]
    box = Poly3DCollection(faces, facecolor="tab:orange", edgecolor="tab:brown", alpha=0.35)
    box.set_gid("platform")
    ax.add_collection3d(box)
    ax.scatter(*points.T, color="tab:brown", s=12, depthshade=False)

    if reference is not None:
        ax.plot(*np.asarray(reference, float).T, "k--", lw=1.0, label="reference", gid="reference")
    if path is not None:
        ax.plot(*np.asarray(path, float).T, color="tab:red", lw=1.2, label="platform", gid="path")
    if reference is not None or path is not None:
        ax.legend(loc="upper left", fontsize="small")
    ax.set(xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    drawn = [anchors, points] + [np.asarray(x, float) for x in (path, reference) if x is not None]
    low, high = np.vstack(drawn).min(axis=0), np.vstack(drawn).max(axis=0)
    extent = np.maximum(high - low, 0.05 * float(np.max(high - low)))
    ax.set(
        xlim=(low[0], low[0] + extent[0]),
        ylim=(low[1], low[1] + extent[1]),
        zlim=(low[2], low[2] + extent[2]),
    )
    ax.set_box_aspect(extent)
    ax.set_title(title or f"{robot.name}: cables coloured by tension")
    return fig


def write_robot_3d(
    file: str | Path, robot: Robot, pose: Pose, tensions: ArrayLike, **kwargs: Any
) -> None:
    """draw_robot_3d saved as a PNG to `file`."""
    draw_robot_3d(robot, pose, tensions, **kwargs).savefig(file, dpi=100)


def _box_edges(lo: np.ndarray, hi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 12 edges of the axis-aligned box lo..hi (corners differing in one axis)."""
    corners = [np.choose(c, [lo, hi]) for c in product((0, 1), repeat=3)]
    return [(a, b) for a, b in combinations(corners, 2) if np.count_nonzero(a != b) == 1]
