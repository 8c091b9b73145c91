"""Rotation R(t) = exp(θ(t)) R0 with θ(t) in R³: world-frame ω and ω̇ in closed form.

d/dt exp(θ) = [J_l(θ) θ̇]× exp(θ), J_l the left Jacobian of SO(3), so the world-frame
rate (DESIGN §3, Ṙ = [ω]× R) is ω = J_l(θ) θ̇ and ω̇ = J_l(θ) θ̈ + (d/dt J_l(θ)) θ̇.
J_l = I + b[θ]× + c[θ]×² with b = (1 - cos x)/x², c = (x - sin x)/x³, x = |θ|.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

_SERIES_BELOW = 0.25  # |θ|² below which the coefficients use their Taylor series
_TERMS = 7  # enough for 1e-17 relative truncation error up to |θ| = 0.5


def _series(offset: int, derivative: bool) -> tuple[float, ...]:
    """Powers of x², highest first: (-1)^k / (2k + offset)!, or for d/dx(..)/x, k >= 1,
    (-1)^k 2k / (2k + offset)! (the coefficient of x^(2k-2))."""
    k0 = int(derivative)
    return tuple(
        (-1) ** k * (2 * k if derivative else 1) / math.factorial(2 * k + offset)
        for k in range(k0 + _TERMS - 1, k0 - 1, -1)
    )


# b = Σ (-1)^k x^2k / (2k+2)!, c = Σ (-1)^k x^2k / (2k+3)!, and β, γ: d/dx of them over x;
# one row per power of x², so that one Horner loop evaluates all four series
_SERIES = tuple(
    zip(_series(2, False), _series(3, False), _series(2, True), _series(3, True), strict=True)
)


def _jl_coefficients(x2: float) -> tuple[float, float, float, float]:
    """(b, c, β, γ) for |θ|² = x2: J_l = I + b[θ]× + c[θ]×², β = b'(x)/x, γ = c'(x)/x.
    x2 may also be an array of samples (then each coefficient is an array)."""
    if isinstance(x2, np.ndarray):
        small = x2 < _SERIES_BELOW
        series = _series_coefficients(x2)
        closed = _closed_coefficients(np.where(small, 1.0, x2), np.sqrt, np.sin, np.cos)
        return tuple(np.where(small, a, b) for a, b in zip(series, closed, strict=True))
    if x2 < _SERIES_BELOW:
        return _series_coefficients(x2)
    return _closed_coefficients(x2, math.sqrt, math.sin, math.cos)


def _series_coefficients(x2: float) -> tuple[float, float, float, float]:
    """(b, c, β, γ) from their Taylor series: the closed forms cancel badly near 0."""
    b = c = beta = gamma = 0.0
    for kb, kc, kbeta, kgamma in _SERIES:  # Horner, highest power first
        b = b * x2 + kb
        c = c * x2 + kc
        beta = beta * x2 + kbeta
        gamma = gamma * x2 + kgamma
    return b, c, beta, gamma


def _closed_coefficients(
    x2: float, sqrt: Callable[[float], float], sin: Callable[[float], float], cos: Callable
) -> tuple[float, float, float, float]:
    """(b, c, β, γ) in closed form, with the math or the numpy functions."""
    x = sqrt(x2)
    s, co = sin(x), cos(x)
    return (
        (1.0 - co) / x2,
        (x - s) / (x2 * x),
        (x * s - 2.0 * (1.0 - co)) / (x2 * x2),
        (3.0 * s - 2.0 * x - x * co) / (x2 * x2 * x),
    )


def left_jacobians(theta: ArrayLike) -> NDArray[np.float64]:
    """J_l(θ) (m, 3, 3) for each row of θ (m, 3), with d/dt exp(θ) = [J_l(θ) θ̇]× exp(θ)
    (the world-frame rate of exp(θ) R0)."""
    th = np.asarray(theta, dtype=float)
    b, c, _, _ = _jl_coefficients(np.einsum("ij,ij->i", th, th))
    x, y, z = th.T
    W = np.zeros((len(th), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -z, y, -x  # [θ]×, row by row
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = z, -y, x
    return np.eye(3) + b[:, None, None] * W + c[:, None, None] * (W @ W)


def angular_rates(
    theta: Sequence[float], theta_dot: Sequence[float], theta_ddot: Sequence[float]
) -> tuple[list[float], list[float]]:
    """World-frame ω and ω̇ of R = exp(θ) R0: ω = J_l θ̇, ω̇ = J_l θ̈ + J̇_l θ̇.  Each
    argument is 3 floats, or 3 arrays of samples (then ω and ω̇ are 3 arrays each).

    J̇_l θ̇ = β s (θ×θ̇) + γ s θ×(θ×θ̇) + c θ̇×(θ×θ̇) with s = θ·θ̇.  Scalar hot path.
    """
    tx, ty, tz = theta
    dx, dy, dz = theta_dot
    ex, ey, ez = theta_ddot
    b, c, beta, gamma = _jl_coefficients(tx * tx + ty * ty + tz * tz)
    ux, uy, uz = ty * dz - tz * dy, tz * dx - tx * dz, tx * dy - ty * dx  # θ × θ̇
    wx, wy, wz = ty * uz - tz * uy, tz * ux - tx * uz, tx * uy - ty * ux  # θ × (θ × θ̇)
    fx, fy, fz = ty * ez - tz * ey, tz * ex - tx * ez, tx * ey - ty * ex  # θ × θ̈
    gx, gy, gz = ty * fz - tz * fy, tz * fx - tx * fz, tx * fy - ty * fx  # θ × (θ × θ̈)
    kx, ky, kz = dy * uz - dz * uy, dz * ux - dx * uz, dx * uy - dy * ux  # θ̇ × (θ × θ̇)
    s = tx * dx + ty * dy + tz * dz
    bs, gs = beta * s, gamma * s
    omega = [dx + b * ux + c * wx, dy + b * uy + c * wy, dz + b * uz + c * wz]
    omega_dot = [
        ex + b * fx + c * gx + bs * ux + gs * wx + c * kx,
        ey + b * fy + c * gy + bs * uy + gs * wy + c * ky,
        ez + b * fz + c * gz + bs * uz + gs * wz + c * kz,
    ]
    return omega, omega_dot
