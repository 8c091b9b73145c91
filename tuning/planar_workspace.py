"""The wrench-feasible workspace of a 4-cable planar robot, for the picture beside
reference8's: the capacity margin (cdpr.wrench_margin) is not tied to six degrees of
freedom, and a planar robot (x, z and the rotation about y; 4 cables, 1 redundant) shows
its shape in one slice.

    python -m tuning.planar_workspace [--png FILE] [--step M]

The robot: a 2 m x 1.5 m frame, anchors at its corners, a 0.2 m x 0.1 m platform of 2 kg
whose cables cross (the upper ones to the platform's far upper corners), tensions 5-100 N,
moments counted at the attachments' RMS radius as reference8's are.
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray

from cdpr.wrench_margin import WrenchMargin, wrench_length

Array = NDArray[np.float64]

ANCHORS = np.array([[-1.0, 1.5], [1.0, 1.5], [-1.0, 0.0], [1.0, 0.0]])  # x, z (m)
ATTACHMENTS = np.array([[0.1, 0.05], [-0.1, 0.05], [-0.1, -0.05], [0.1, -0.05]])
MASS, GRAVITY = 2.0, 9.81  # kg, m/s^2
T_MIN, T_MAX = 5.0, 100.0  # N


def margins(x: Array, z: Array, theta: float = 0.0) -> Array:
    """The capacity margin (N) at each position (x, z: equal shapes) at rotation theta."""
    c, s = np.cos(theta), np.sin(theta)
    r = ATTACHMENTS @ np.array([[c, s], [-s, c]])  # R b, rows
    points = np.stack([x.ravel(), z.ravel()], axis=1)
    d = points[:, None, :] + r[None] - ANCHORS[None]  # anchor -> attachment
    u = d / np.linalg.norm(d, axis=2, keepdims=True)
    moment = r[None, :, 1] * u[..., 0] - r[None, :, 0] * u[..., 1]  # (r x u) about y
    jacobians = np.concatenate([u, moment[..., None]], axis=2)  # rows [u_x, u_z, m_y]
    needed = np.tile([0.0, -MASS * GRAVITY, 0.0], (len(points), 1))  # Lambda^T t = -mu
    model = WrenchMargin(np.full(4, T_MIN), np.full(4, T_MAX), wrench_length(r), dof=3)
    return model.margins(jacobians, needed).reshape(x.shape)


def plot(path: str, step: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.arange(-0.9, 0.9 + 1e-9, step)
    zs = np.arange(0.1, 1.4 + 1e-9, step)
    x, z = np.meshgrid(xs, zs)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
    for ax, theta in zip(axes, (0.0, 0.3), strict=True):
        m = margins(x, z, theta)
        ax.set_facecolor("0.85")
        image = ax.imshow(
            np.where(m > 0.0, m, np.nan),
            origin="lower",
            extent=(xs[0], xs[-1], zs[0], zs[-1]),
            vmin=0.0,
            cmap="viridis",
        )
        ax.plot(*ANCHORS.T, "ks")
        ax.set(title=f"rotation {theta:g} rad", xlabel="x (m)", ylabel="z (m)", aspect="equal")
        fig.colorbar(image, ax=ax, label="capacity margin (N)")
    fig.suptitle("a 4-cable planar robot: grey cannot hold its 2 kg platform at rest")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--png", default="docs/images/workspace-planar4.png")
    parser.add_argument("--step", type=float, default=0.01)
    args = parser.parse_args()
    plot(args.png, args.step)


if __name__ == "__main__":
    main()
