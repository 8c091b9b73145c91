"""Static equilibrium tensions: the cable tensions that hold a pose at rest.

For initialising the plant (and tests) at an equilibrium, not the controller's
tension distribution (DESIGN §6 lives in cdpr): it uses the model's own Λ and μ.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from cdpr import Pose, Robot

_ZERO_TWIST = np.zeros(6)
_TOLERANCE = 1e-9  # N, and relative to the wrench


def equilibrium_tensions(
    robot: Robot, pose: Pose, reference: ArrayLike | None = None
) -> NDArray[np.float64]:
    """Tensions t >= t_min with -Λᵀ t = μ(pose, 0), closest to `reference` (default
    mid-range, (t_min + force_max) / 2).  ValueError when no such tensions exist.

    Closed form (the reference corrected by the minimum-norm change) when that is
    feasible, else the small QP by SLSQP; the equality is then restored exactly.
    """
    Lam = robot.jacobian(pose)
    w = -robot.bias_wrench(pose, _ZERO_TWIST)  # Λᵀ t = -μ
    t_ref = (
        0.5 * (robot.t_min + robot.force_max)
        if reference is None
        else np.broadcast_to(np.asarray(reference, dtype=float), robot.t_min.shape)
    )
    pinv = np.linalg.pinv(Lam.T)
    t = t_ref + pinv @ (w - Lam.T @ t_ref)
    if np.any(t < robot.t_min) and robot.n_cables > 6:
        res = minimize(
            lambda x: float((x - t_ref) @ (x - t_ref)),
            np.maximum(t, robot.t_min),
            jac=lambda x: 2.0 * (x - t_ref),
            constraints=[{"type": "eq", "fun": lambda x: Lam.T @ x - w, "jac": lambda x: Lam.T}],
            bounds=[(lo, None) for lo in robot.t_min],
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 500},
        )
        t = res.x + pinv @ (w - Lam.T @ res.x)
    residual = float(np.max(np.abs(Lam.T @ t - w)))
    scale = max(1.0, float(np.max(np.abs(w))))
    if np.any(t < robot.t_min - _TOLERANCE) or residual > _TOLERANCE * scale:
        raise ValueError(
            f"{robot.name}: no tensions >= t_min hold {pose} at rest "
            f"(best {np.round(t, 3).tolist()} N, wrench residual {residual:.3g})"
        )
    return t
