"""Small-signal analysis of the single-actuator loop: the paper's tuning view (§4, Lemma 1).

The rig (one actuator, elastic cable, passive load) is linearised at rest
(SingleActuatorRig.linear_system), sampled with a zero-order hold at the loop period,
and closed with the discretised single-actuator controller scaled by the effective
mass m = m0 + load (the paper's f_c = m a_c).  The closed loop's poles say whether the
gains are stable for that load and how fast it settles; over m in [m0, m_max] they
show the robust range, and with m = a robot's modal masses they predict its modes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from cdpr.description import ActuatorSpec
from cdpr.single_actuator import Discretisation, LinearController
from sim_bus.plant.config import PlantConfig
from sim_bus.rig import OUTPUTS, SingleActuatorRig

Array = NDArray[np.float64]


class LoopModes(NamedTuple):
    """The sampled closed loop of one actuator with effective mass `mass`."""

    mass: float
    spectral_radius: float  # < 1: stable
    poles: Array  # continuous-time equivalents log(z)/T (1/s), slowest first
    settling_time: float  # s, step in l_r until |error| stays within 2 % (inf: never)
    overshoot: float  # fraction of the step

    @property
    def stable(self) -> bool:
        return self.spectral_radius < 1.0


def loop_modes(
    actuator: ActuatorSpec,
    mass: float,
    controller: LinearController,
    period: float,
    config: PlantConfig | None = None,
    cable_length: float = 2.0,
    preload: float = 100.0,
    method: Discretisation = "zoh",
    horizon: float = 10.0,
) -> LoopModes:
    """Closed-loop poles and step response of the rig with effective mass `mass`
    (>= m0, finite), over `horizon` seconds."""
    if not actuator.m0 <= mass < math.inf:
        raise ValueError(f"mass must be in [m0 = {actuator.m0}, inf), got {mass}")
    rig = SingleActuatorRig(actuator, mass - actuator.m0, config, cable_length, preload)
    A_cl, B_ref, length = closed_loop_matrices(rig, controller, period, mass, method)
    z = np.linalg.eigvals(A_cl)
    rho = float(np.max(np.abs(z)))
    with np.errstate(divide="ignore"):
        poles = np.log(z.astype(complex)) / period
    poles = poles[np.argsort(-poles.real)]
    settling, overshoot = math.inf, math.inf
    if rho < 1.0:
        steps = round(horizon / period)
        x = np.zeros(A_cl.shape[0])
        error = np.empty(steps)
        for k in range(steps):
            x = A_cl @ x + B_ref
            error[k] = length @ x - 1.0
        outside = np.flatnonzero(np.abs(error) > 0.02)
        settling = (outside[-1] + 2) * period if outside.size else period
        overshoot = max(0.0, float(error.max()))
    return LoopModes(float(mass), rho, poles, settling, overshoot)


def closed_loop_matrices(
    rig: SingleActuatorRig,
    controller: LinearController,
    period: float,
    mass: float,
    method: Discretisation = "zoh",
) -> tuple[Array, Array, Array]:
    """The sampled loop [plant; controller] with f_c = mass * a: state matrix, the
    input column of a unit step in the length reference, and the length output row.

    The controller reads the length and the rate as the drive reports it: a difference
    of lengths over the encoder's velocity window when that window is a whole number of
    loop periods (one delayed length sample per period of window), else the true rate.
    """
    plant = rig.linear_system()
    Phi, Gamma, C, _, _ = signal.cont2discrete(
        (plant.A, plant.B, plant.C, plant.D), period, method="zoh"
    )
    length = C[OUTPUTS.index("length")]
    rate = C[OUTPUTS.index("rate")]
    window = rig.config.encoder.velocity_window_steps * rig.config.step
    lags = round(window / period)
    n = Phi.shape[0]
    if lags >= 1 and abs(lags * period - window) < 1e-12:
        # augment with the last `lags` length samples: z_j[k+1] = z_{j-1}[k], z_0 = l
        size = n + lags
        P = np.zeros((size, size))
        P[:n, :n] = Phi
        P[n, :n] = length
        for j in range(1, lags):
            P[n + j, n + j - 1] = 1.0
        G = np.vstack([Gamma, np.zeros((lags, 1))])
        L = np.concatenate([length, np.zeros(lags)])
        V = L.copy()
        V[n + lags - 1] -= 1.0
        V /= window
        Phi, Gamma, length, rate = P, G, L, V
    Y = np.vstack([length, rate])[: controller.order]
    loop = controller.discretise(period, 1, method)
    Ad, Bd, Cd, Dd = loop.Ad, loop.Bd, loop.Cd, loop.Dd
    size, nc = Phi.shape[0], Ad.shape[0]
    A_cl = np.zeros((size + nc, size + nc))
    A_cl[:size, :size] = Phi + mass * Gamma @ (Dd @ Y)
    A_cl[:size, size:] = mass * Gamma @ Cd
    A_cl[size:, :size] = Bd @ Y
    A_cl[size:, size:] = Ad
    # a reference l_r enters as error -l_r on the length channel
    B_ref = -np.concatenate([mass * Gamma @ Dd[:, :1], Bd[:, :1]]).reshape(-1)
    return A_cl, B_ref, np.concatenate([length, np.zeros(nc)])


def robust_mass_range(
    actuator: ActuatorSpec,
    controller: LinearController,
    period: float,
    config: PlantConfig | None = None,
    cable_length: float = 2.0,
    preload: float = 100.0,
    largest: float = 1e4,
    points: int = 60,
) -> list[LoopModes]:
    """loop_modes over effective masses log-spaced from m0 to `largest` (kg)."""
    masses = np.geomspace(actuator.m0, largest, points)
    return [
        loop_modes(actuator, float(m), controller, period, config, cable_length, preload)
        for m in masses
    ]
