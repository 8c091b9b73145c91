"""Readable numpy reference of the model, kept beside the scalar fast paths.

Written straight from DESIGN §3 with vectors and block matrices, for the tests to
hold the fast code equal to, and for readers who want the maths without unrolling.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.so3 import hat

Array = NDArray[np.float64]


def attachment_offsets(robot: Robot, pose: Pose) -> Array:
    """r_k = R b_k, one row per cable."""
    return robot.geometry.attachments @ pose.rotation.T


def pulley_cable(d: Array, radius: float, axis: Array) -> tuple[Array, Array, Array, Array, Array]:
    """Standard pulley model for d = B - a (one per row, or one vector): (length, u, n_P,
    free length, x_p).

    In the plane spanned by the swivel axis z and x_p (towards B), the pulley centre
    sits at a + r x_p; the cable leaves it at P where the radius n_P is normal to B - P.
    """
    z = np.asarray(axis, dtype=float)
    along = d @ z
    e = d - along[..., None] * z
    rho = np.linalg.norm(e, axis=-1)
    x_p = e / rho[..., None]
    w0, w1 = rho - radius, along  # B - centre, in (x_p, z) coordinates
    wn = np.hypot(w0, w1)
    free = np.sqrt(wn**2 - radius**2)
    theta_p = np.arctan2(w1, w0) + np.arccos(radius / wn)
    s, c = np.sin(theta_p)[..., None], np.cos(theta_p)[..., None]
    u = s * x_p - c * z
    n_p = c * x_p + s * z
    return radius * (np.pi - theta_p) + free, u, n_p, free, x_p


def cable_segments(
    robot: Robot, positions: ArrayLike, rotations: Array
) -> tuple[Array, Array, Array, Array]:
    """At the poses (positions: N x 3; rotations: N x 3 x 3, or one 3 x 3 for all): cable
    lengths (N x n), the free segments' unit directions u (N x n x 3, towards the
    platform), where the free segments start (the anchor, or the pulley's leave point)
    and where they end (the attachments), N x n x 3 each, world frame."""
    geometry = robot.geometry
    R = np.asarray(rotations, dtype=float)
    b = geometry.attachments
    r = b @ R.T if R.ndim == 2 else np.einsum("nij,kj->nki", R, b)
    ends = np.asarray(positions, dtype=float)[:, None, :] + r
    d = ends - geometry.anchors
    lengths = np.linalg.norm(d, axis=-1)
    u = d / lengths[..., None]
    starts = np.broadcast_to(geometry.anchors, d.shape).copy()
    for k, pulley in enumerate(geometry.pulleys):
        if pulley is not None:
            lengths[:, k], u[:, k], _, free, _ = pulley_cable(d[:, k], pulley[0], pulley[1])
            starts[:, k] = ends[:, k] - free[:, None] * u[:, k]
    return lengths, u, starts, ends


def lengths_directions(robot: Robot, pose: Pose) -> tuple[Array, Array]:
    """Cable lengths and unit directions u_k of the free segments at the attachments."""
    lengths, u, _, _ = cable_segments(robot, pose.position[None], pose.rotation)
    return lengths[0], u[0]


def jacobian(robot: Robot, pose: Pose) -> Array:
    """Lambda: rows [u_k, r_k x u_k]."""
    _, u = lengths_directions(robot, pose)
    return np.hstack([u, np.cross(attachment_offsets(robot, pose), u)])


def bias_accel(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """c_k = u_k . (w x (w x r_k)) + xd_k^T H_k xd_k, H_k the Hessian of l_k in B."""
    phi = np.asarray(twist, dtype=float)
    v, w = phi[:3], phi[3:]
    r = attachment_offsets(robot, pose)
    d = pose.position + r - robot.geometry.anchors
    out = np.empty(robot.n_cables)
    for k, pulley in enumerate(robot.geometry.pulleys):
        xd = v + np.cross(w, r[k])
        if pulley is None:
            ell = np.linalg.norm(d[k])
            u = d[k] / ell
            H = (np.eye(3) - np.outer(u, u)) / ell
        else:
            z = np.array(pulley[1])
            _, u, n_p, free, x_p = pulley_cable(d[k], pulley[0], z)
            rho = np.linalg.norm(d[k] - (d[k] @ z) * z)
            n = np.cross(z, x_p)
            H = np.outer(n_p, n_p) / free + (u @ x_p) / rho * np.outer(n, n)
        out[k] = u @ np.cross(w, np.cross(w, r[k])) + xd @ H @ xd
    return out


def platform_mass_matrix(robot: Robot, pose: Pose) -> Array:
    """M_p = [[m I, -m[c]x], [m[c]x, I_c - m[c]x[c]x]]."""
    m = robot.platform.mass
    R = pose.rotation
    C = hat(R @ np.array(robot.platform.center_of_mass))
    I_c = R @ robot.platform.inertia @ R.T
    return np.block([[m * np.eye(3), -m * C], [m * C, I_c - m * C @ C]])


def platform_bias(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """mu_p = [m w x (w x c) - m g ; w x (I_c w) + m c x (w x (w x c)) - m c x g]."""
    m = robot.platform.mass
    g = np.array(robot.platform.gravity)
    R = pose.rotation
    c = R @ np.array(robot.platform.center_of_mass)
    I_c = R @ robot.platform.inertia @ R.T
    w = np.asarray(twist, dtype=float)[3:]
    wwc = np.cross(w, np.cross(w, c))
    return np.concatenate([m * wwc - m * g, np.cross(w, I_c @ w) + m * np.cross(c, wwc - g)])


def mass_matrix(robot: Robot, pose: Pose) -> Array:
    """M = M_p + Lambda^T diag(m0) Lambda."""
    Lam = jacobian(robot, pose)
    return platform_mass_matrix(robot, pose) + Lam.T @ np.diag(robot.m0) @ Lam


def bias_wrench(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """mu = mu_p + Lambda^T diag(m0) c."""
    Lam = jacobian(robot, pose)
    return platform_bias(robot, pose, twist) + Lam.T @ (robot.m0 * bias_accel(robot, pose, twist))
