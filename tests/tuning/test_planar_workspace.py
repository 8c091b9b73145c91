"""The planar example's margins against scipy's HiGHS LP on its own geometry."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linprog

from tuning.planar_workspace import ANCHORS, ATTACHMENTS, GRAVITY, MASS, T_MAX, T_MIN, margins


def test_the_planar_verdicts_are_the_lp_s() -> None:
    rng = np.random.default_rng(3)
    x, z = rng.uniform(-0.9, 0.9, 300), rng.uniform(0.1, 1.4, 300)
    found = margins(x, z)
    compared = inside = 0
    for xi, zi, m in zip(x, z, found, strict=True):
        if abs(m) < 0.5:
            continue
        d = np.array([xi, zi]) + ATTACHMENTS - ANCHORS
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
        moment = ATTACHMENTS[:, 1] * u[:, 0] - ATTACHMENTS[:, 0] * u[:, 1]
        lp = linprog(
            np.zeros(4),
            A_eq=np.vstack([u[:, 0], u[:, 1], moment]),
            b_eq=[0.0, -MASS * GRAVITY, 0.0],
            bounds=[(T_MIN, T_MAX)] * 4,
            method="highs",
        )
        assert (lp.status == 0) == (m > 0), (xi, zi, m)
        compared += 1
        inside += m > 0
    assert compared > 250 and 30 < inside < compared - 30
