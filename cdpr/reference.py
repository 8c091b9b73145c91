"""Readable numpy reference of the model, kept beside the scalar fast paths.

Written straight from DESIGN §3 with vectors and block matrices, for the tests to
hold the fast code equal to, and for readers who want the maths without unrolling.
Batched over poses (N x ...): the path timing takes the model at a thousand grid points
at once (`model_terms`: 3.5 us a pose over a 1,200-point grid, where the scalar
Robot.model_terms takes 26 us a pose, one by one).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.so3 import hat

Array = NDArray[np.float64]


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


def cross(a: ArrayLike, b: ArrayLike) -> Array:
    """a x b over the last axis, broadcast (np.cross without its general axis handling,
    which costs it three times as much on a path's grid)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def jacobians(robot: Robot, positions: ArrayLike, rotations: Array) -> Array:
    """Lambda at each pose (N x n x 6): rows [u_k, r_k x u_k]."""
    positions = np.asarray(positions, dtype=float)
    _, u, _, ends = cable_segments(robot, positions, rotations)
    return _jacobians(u, ends - positions[:, None, :])


def _jacobians(u: Array, r: Array) -> Array:
    return np.concatenate([u, cross(r, u)], axis=-1)


def bias_accels(robot: Robot, positions: ArrayLike, rotations: Array, twists: ArrayLike) -> Array:
    """c at each pose and twist (N x n): c_k = u_k . (w x (w x r_k)) + xd_k^T H_k xd_k,
    H_k the Hessian of l_k in B: (I - u u^T) / l for a cable from its anchor,
    n_P n_P^T / free + (u . x_p) / rho n n^T over a pulley (n = z x x_p)."""
    positions = np.asarray(positions, dtype=float)
    lengths, u, _, ends = cable_segments(robot, positions, rotations)
    return _bias_accels(robot, lengths, u, ends, positions, twists)


def _bias_accels(
    robot: Robot, lengths: Array, u: Array, ends: Array, positions: Array, twists: ArrayLike
) -> Array:
    """bias_accels from the poses' cable segments (cable_segments)."""
    twists = np.asarray(twists, dtype=float)
    geometry = robot.geometry
    r = ends - positions[:, None, :]
    v, w = twists[:, None, :3], twists[:, None, 3:]
    xd = v + cross(w, r)
    along = np.sum(u * xd, axis=-1)
    quad = (np.sum(xd * xd, axis=-1) - along**2) / lengths
    for k, pulley in enumerate(geometry.pulleys):
        if pulley is not None:
            z = np.asarray(pulley[1], dtype=float)
            d = ends[:, k] - geometry.anchors[k]
            _, u_k, n_p, free, x_p = pulley_cable(d, pulley[0], z)
            rho = np.linalg.norm(d - (d @ z)[:, None] * z, axis=-1)
            n = cross(z, x_p)
            across = np.sum(u_k * x_p, axis=-1) / rho
            quad[:, k] = (
                np.sum(n_p * xd[:, k], axis=-1) ** 2 / free
                + across * np.sum(n * xd[:, k], axis=-1) ** 2
            )
    return np.sum(u * cross(w, cross(w, r)), axis=-1) + quad


def platform_terms(robot: Robot, rotations: Array, twists: ArrayLike) -> tuple[Array, Array]:
    """M_p = [[m I, -m[c]x], [m[c]x, I_c - m[c]x[c]x]] (N x 6 x 6) and mu_p = [m w x (w x
    c) - m g ; w x (I_c w) + m c x (w x (w x c)) - m c x g] (N x 6) at each rotation
    (N x 3 x 3) and twist (N x 6)."""
    platform = robot.platform
    m, g = platform.mass, np.array(platform.gravity)
    R = np.asarray(rotations, dtype=float)
    c = R @ np.array(platform.center_of_mass)
    C = hat(c)
    I_c = R @ platform.inertia @ np.swapaxes(R, -1, -2)
    top = np.concatenate([np.broadcast_to(m * np.eye(3), C.shape), -m * C], axis=-1)
    bottom = np.concatenate([m * C, I_c - m * C @ C], axis=-1)
    w = np.asarray(twists, dtype=float)[:, 3:]
    wwc = cross(w, cross(w, c))
    I_w = np.matmul(I_c, w[:, :, None])[:, :, 0]
    mu = np.concatenate([m * wwc - m * g, cross(w, I_w) + m * cross(c, wwc - g)], axis=-1)
    return np.concatenate([top, bottom], axis=-2), mu


def model_terms(
    robot: Robot, positions: ArrayLike, rotations: Array, twists: ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """Robot.model_terms at many poses at once (a path's grid): Lambda (N x n x 6), c
    (N x n), M = M_p + Lambda^T diag(m0) Lambda (N x 6 x 6) and mu = mu_p + Lambda^T
    diag(m0) c (N x 6)."""
    positions = np.asarray(positions, dtype=float)
    lengths, u, _, ends = cable_segments(robot, positions, rotations)
    Lam = _jacobians(u, ends - positions[:, None, :])
    c = _bias_accels(robot, lengths, u, ends, positions, twists)
    M_p, mu_p = platform_terms(robot, rotations, twists)
    weighted = Lam * robot.m0[:, None]
    M = M_p + np.swapaxes(Lam, 1, 2) @ weighted
    mu = mu_p + np.matmul((robot.m0 * c)[:, None, :], Lam)[:, 0, :]
    return Lam, c, M, mu


def _one(pose: Pose) -> tuple[Array, Array]:
    return pose.position[None], pose.rotation[None]


def jacobian(robot: Robot, pose: Pose) -> Array:
    """Lambda: rows [u_k, r_k x u_k]."""
    return jacobians(robot, *_one(pose))[0]


def bias_accel(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """c at one pose and twist (bias_accels)."""
    return bias_accels(robot, *_one(pose), np.asarray(twist, dtype=float)[None])[0]


def platform_mass_matrix(robot: Robot, pose: Pose) -> Array:
    """M_p at one pose (platform_terms)."""
    return platform_terms(robot, pose.rotation[None], np.zeros((1, 6)))[0][0]


def platform_bias(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """mu_p at one pose and twist (platform_terms)."""
    return platform_terms(robot, pose.rotation[None], np.asarray(twist, dtype=float)[None])[1][0]


def mass_matrix(robot: Robot, pose: Pose) -> Array:
    """M = M_p + Lambda^T diag(m0) Lambda."""
    return model_terms(robot, *_one(pose), np.zeros((1, 6)))[2][0]


def bias_wrench(robot: Robot, pose: Pose, twist: ArrayLike) -> Array:
    """mu = mu_p + Lambda^T diag(m0) c."""
    return model_terms(robot, *_one(pose), np.asarray(twist, dtype=float)[None])[3][0]
