"""Platform dynamics in mixed coordinates (DESIGN §3), scalar hot path.

tau = M alpha + mu with M = M_p + Lambda^T D Lambda and mu = mu_p + Lambda^T D c,
D = diag(m0_k) (the actuators' effective no-load masses).  The platform part, with
c = R c_b the centre of mass offset and I_c = R I_b R^T the inertia about it:

    M_p  = [[m I, -m[c]x], [m[c]x, I_c - m[c]x[c]x]]
    mu_p = [m w x (w x c) - m g ; w x (I_c w) + m c x (w x (w x c)) - m c x g]

mu carries +dV/deta: gravity is compensated (the paper's "-dv/deta" is a sign slip).

The scalar code uses the inertia about p, I_p = I_c - m[c]x[c]x = R I_pb R^T, whose
platform-frame value I_pb = I_b + m (|c_b|^2 I - c_b c_b^T) is constant, and
w x (I_c w) + m c x (w x (w x c)) = w x (I_p w) (the terms beyond w x (I_c w) both
equal m (w . c)(c x w)): the same M_p and mu_p with fewer operations.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray


class PlatformInertia:
    """Mass m, centre of mass c_b and inertia I_b (about the CoM, platform frame), gravity g."""

    def __init__(
        self,
        mass: float,
        center_of_mass: Sequence[float],
        inertia: NDArray[np.float64],
        gravity: Sequence[float],
    ) -> None:
        self.mass = float(mass)
        self.center_of_mass = tuple(float(c) for c in center_of_mass)
        self.inertia = np.array(inertia, dtype=float)
        self.gravity = tuple(float(c) for c in gravity)
        cb = np.array(self.center_of_mass)
        about_p = self.inertia + self.mass * (cb @ cb * np.eye(3) - np.outer(cb, cb))
        self._I_p = tuple(about_p.reshape(9).tolist())  # I_pb, see the module docstring
        # [m, c_b, I_pb row-major, g]: what the compiled kernels take (cdpr.compiled_model)
        self.rows = np.array([self.mass, *self.center_of_mass, *self._I_p, *self.gravity])

    @property
    def inertia_about_p(self) -> tuple[float, ...]:
        """I_pb, the inertia about p (platform frame), row-major."""
        return self._I_p

    def mass_and_bias(self, R: Sequence[float], phi: Sequence[float]) -> list[float]:
        """[M_p | mu_p], 6 x 7 row-major as 42 floats, for rotation R and twist phi."""
        m = self.mass
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
        bx, by, bz = self.center_of_mass
        cx = r00 * bx + r01 * by + r02 * bz
        cy = r10 * bx + r11 * by + r12 * bz
        cz = r20 * bx + r21 * by + r22 * bz
        i00, i01, i02, i10, i11, i12, i20, i21, i22 = self._I_p
        # T = R I_pb, then I_p = T R^T (symmetric)
        t00 = r00 * i00 + r01 * i10 + r02 * i20
        t01 = r00 * i01 + r01 * i11 + r02 * i21
        t02 = r00 * i02 + r01 * i12 + r02 * i22
        t10 = r10 * i00 + r11 * i10 + r12 * i20
        t11 = r10 * i01 + r11 * i11 + r12 * i21
        t12 = r10 * i02 + r11 * i12 + r12 * i22
        t20 = r20 * i00 + r21 * i10 + r22 * i20
        t21 = r20 * i01 + r21 * i11 + r22 * i21
        t22 = r20 * i02 + r21 * i12 + r22 * i22
        p00 = t00 * r00 + t01 * r01 + t02 * r02
        p01 = t00 * r10 + t01 * r11 + t02 * r12
        p02 = t00 * r20 + t01 * r21 + t02 * r22
        p11 = t10 * r10 + t11 * r11 + t12 * r12
        p12 = t10 * r20 + t11 * r21 + t12 * r22
        p22 = t20 * r20 + t21 * r21 + t22 * r22
        mcx, mcy, mcz = m * cx, m * cy, m * cz
        wx, wy, wz = phi[3], phi[4], phi[5]
        gx, gy, gz = self.gravity
        # a = w x (w x c) - g: the acceleration of the CoM relative to p, and gravity
        vx = wy * cz - wz * cy
        vy = wz * cx - wx * cz
        vz = wx * cy - wy * cx
        ax = wy * vz - wz * vy - gx
        ay = wz * vx - wx * vz - gy
        az = wx * vy - wy * vx - gz
        # I_p w, then w x (I_p w) - m c x g
        hx = p00 * wx + p01 * wy + p02 * wz
        hy = p01 * wx + p11 * wy + p12 * wz
        hz = p02 * wx + p12 * wy + p22 * wz
        return [
            m, 0.0, 0.0, 0.0, mcz, -mcy, m * ax,
            0.0, m, 0.0, -mcz, 0.0, mcx, m * ay,
            0.0, 0.0, m, mcy, -mcx, 0.0, m * az,
            0.0, -mcz, mcy, p00, p01, p02, wy * hz - wz * hy + mcz * gy - mcy * gz,
            mcz, 0.0, -mcx, p01, p11, p12, wz * hx - wx * hz + mcx * gz - mcz * gx,
            -mcy, mcx, 0.0, p02, p12, p22, wx * hy - wy * hx + mcy * gx - mcx * gy,
        ]  # fmt: skip


def modal_masses(M: NDArray[np.float64], Lambda: NDArray[np.float64]) -> NDArray[np.float64]:
    """m_i = 1 / eig(M^-1 Lambda^T Lambda), ascending; inf where Lambda^T Lambda is singular.

    Solved as the symmetric-definite problem Lambda^T Lambda v = lambda M v, whose
    eigenvalues are real and lie in [0, 1/min m0] (the paper's Lemma 1).
    """
    from scipy.linalg import eigh

    lam = eigh(Lambda.T @ Lambda, M, eigvals_only=True)
    scale = float(np.max(lam)) if lam.size else 0.0
    with np.errstate(divide="ignore"):
        masses = np.where(lam > 1e-12 * max(scale, 1e-300), 1.0 / np.maximum(lam, 1e-300), np.inf)
    return np.sort(masses)
