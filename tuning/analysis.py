"""Small-signal analysis of the single-actuator loop: the paper's tuning view (§4, Lemma 1).

The rig (one actuator, elastic cable, passive load) is linearised at rest
(SingleActuatorRig.linear_system), sampled with a zero-order hold at the loop period,
and closed with the discretised single-actuator controller scaled by the effective
mass m = m0 + load (the paper's f_c = m a_c).  The closed loop's poles say whether the
gains are stable for that load and how fast it settles; over m in [m0, m_max] they
show the robust range, and with m = a robot's modal masses they predict its modes.
Commands that take effect late (the drives apply them a latency after the sample they
answer) join the loop's state, so the same poles show how much delay the gains bear.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import linalg

from cdpr.description import ActuatorSpec
from cdpr.single_actuator import Discretisation, LinearController
from sim_bus.plant.config import PlantConfig
from sim_bus.plant.rig import OUTPUTS, SingleActuatorRig

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


class Rig(NamedTuple):
    """One actuator's rig as the analysis sees it: actuator, controller, loop period and
    discretisation, plant model, cable length (m) and preload (N), and whether the
    controller reads the true rate (closed_loop_matrices); the load varies."""

    actuator: ActuatorSpec
    controller: LinearController
    period: float
    method: Discretisation = "zoh"
    config: PlantConfig | None = None
    cable_length: float = 2.0
    preload: float = 100.0
    true_rate: bool = False

    def matrices(self, mass: float, latency: float = 0.0) -> tuple[Array, Array, Array]:
        """closed_loop_matrices with effective mass `mass` (>= m0, finite)."""
        m0 = self.actuator.m0
        if not m0 <= mass < math.inf:
            raise ValueError(f"mass must be in [m0 = {m0}, inf), got {mass}")
        rig = SingleActuatorRig(
            self.actuator, mass - m0, self.config, self.cable_length, self.preload
        )
        return closed_loop_matrices(
            rig, self.controller, self.period, mass, self.method, latency, self.true_rate
        )

    def stable(self, mass: float, latency: float = 0.0) -> bool:
        """Is the loop with effective mass `mass` stable, its commands `latency` s late?"""
        return bool(np.max(np.abs(np.linalg.eigvals(self.matrices(mass, latency)[0]))) < 1.0)

    def loop(self, mass: float, latency: float = 0.0, horizon: float = 10.0) -> LoopModes:
        """Closed-loop poles and step response with effective mass `mass` (>= m0,
        finite), over `horizon` seconds, the commands applied `latency` s late."""
        A_cl, B_ref, length = self.matrices(mass, latency)
        period = self.period
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

    def sweep(self, largest: float = 1e4, points: int = 60) -> list[LoopModes]:
        """loop over effective masses log-spaced from m0 to `largest` (kg)."""
        return [self.loop(float(m)) for m in np.geomspace(self.actuator.m0, largest, points)]


def closed_loop_matrices(
    rig: SingleActuatorRig,
    controller: LinearController,
    period: float,
    mass: float,
    method: Discretisation = "zoh",
    latency: float = 0.0,
    true_rate: bool = False,
) -> tuple[Array, Array, Array]:
    """The sampled loop [plant; controller] with f_c = mass * a: state matrix, the
    input column of a unit step in the length reference, and the length output row.

    The controller reads the length and the rate as the drive reports it: a difference
    of lengths over the encoder's velocity window when that window is a whole number of
    loop periods (one delayed length sample per period of window), else, or with
    `true_rate` (a twist estimate whose low frequencies come from the poses, as
    ParallelController's with a cable stiffness), the true rate.

    The command computed from the sample at t_k takes effect at t_k + `latency` and is
    held until the next one does (tuning.lockstep's `latency`); the commands still on
    their way join the state, and a fraction of a period splits the hold.
    """
    if not 0.0 <= latency < math.inf:
        raise ValueError(f"latency must be a finite time >= 0, got {latency}")
    plant = rig.linear_system()
    d, fraction = divmod(latency / period, 1.0)
    d = int(d)
    if fraction < 1e-9 or fraction > 1.0 - 1e-9:  # a whole number of periods
        d, fraction = d + round(fraction), 0.0
    # over [t_k, t_k+1): u[k-d-1] for fraction * period, then u[k-d]
    Phi, Gamma_new = _zoh(plant.A, plant.B, period * (1.0 - fraction))
    Phi_old, Gamma_old = _zoh(plant.A, plant.B, period * fraction)
    Phi, Gamma_old = Phi @ Phi_old, Phi @ Gamma_old
    C = plant.C
    length = C[OUTPUTS.index("length")]
    rate = C[OUTPUTS.index("rate")]
    window = rig.config.encoder.velocity_window_steps * rig.config.step
    lags = round(window / period)
    n = Phi.shape[0]
    if not true_rate and lags >= 1 and abs(lags * period - window) < 1e-12:
        # augment with the last `lags` length samples: z_j[k+1] = z_{j-1}[k], z_0 = l
        size = n + lags
        P = np.zeros((size, size))
        P[:n, :n] = Phi
        P[n, :n] = length
        for j in range(1, lags):
            P[n + j, n + j - 1] = 1.0
        L = np.concatenate([length, np.zeros(lags)])
        V = L.copy()
        V[n + lags - 1] -= 1.0
        V /= window
        Phi, length, rate = P, L, V
        Gamma_new, Gamma_old = (np.vstack([g, np.zeros((lags, 1))]) for g in (Gamma_new, Gamma_old))
    Y = np.vstack([length, rate])[: controller.order]
    loop = controller.discretise(period, 1, method)
    Ad, Bd, Cd, Dd = loop.Ad, loop.Bd, loop.Cd, loop.Dd
    size, nc = Phi.shape[0], Ad.shape[0]
    queued = d + (1 if fraction else 0)  # commands computed 1..queued cycles ago
    total = size + nc + queued
    # u[k] = mass (Cd x_c + Dd e), e = Y x_p - [l_r, 0]: a row over the state
    command = np.concatenate([mass * (Dd @ Y)[0], mass * Cd[0], np.zeros(queued)])
    u_ref = -mass * Dd[0, 0]  # the reference's share of u[k] per unit l_r

    def past(j: int) -> tuple[Array, float]:
        """u[k-j] as (row over the state, reference share)."""
        if j == 0:
            return command, u_ref
        row = np.zeros(total)
        row[size + nc + j - 1] = 1.0
        return row, 0.0

    A_cl = np.zeros((total, total))
    B_ref = np.zeros(total)
    A_cl[:size, :size] = Phi
    for gamma, j in ((Gamma_new[:, 0], d), (Gamma_old[:, 0], d + 1)):
        if j > queued:  # no share (a whole number of periods)
            continue
        row, ref = past(j)
        A_cl[:size] += np.outer(gamma, row)
        B_ref[:size] += ref * gamma
    A_cl[size : size + nc, :size] = Bd @ Y
    A_cl[size : size + nc, size : size + nc] = Ad
    B_ref[size : size + nc] = -Bd[:, 0]  # a reference l_r enters as error -l_r
    if queued:
        A_cl[size + nc] = command
        B_ref[size + nc] = u_ref
        for j in range(1, queued):
            A_cl[size + nc + j, size + nc + j - 1] = 1.0
    return A_cl, B_ref, np.concatenate([length, np.zeros(nc + queued)])


def _zoh(A: Array, B: Array, duration: float) -> tuple[Array, Array]:
    """exp(A t) and the integral of exp(A s) B over [0, t]: a held input's effect."""
    n, m = B.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n] = A * duration
    block[:n, n:] = B * duration
    E = linalg.expm(block)
    return E[:n, :n], E[:n, n:]
