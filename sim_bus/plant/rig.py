"""Single-actuator rig: one winch pulling a passive mass through an elastic cable.

The paper (§4) tunes the single-actuator controller on one actuator carrying a passive
load, and says the rig must include a cable with the robot's stretch (in prototypes,
PID gains tuned without it went unstable on the robot).  The rig uses the robot
plant's own winch code (sim_bus.plant.winch), so it has exactly the same actuator
model, drum, friction, brake, saturation, encoders and cable law.  It answers
VirtualRobot's plant calls (set_brake, set_drive_enabled, break_cable with cable index
0), so the simulator can put it behind the same CAN device code as the robot (sim.rig:
`cdprd tune` identifies it over the bus).

The load moves along the cable; y is its distance from the drum exit, i.e. the
geometric cable length L.  With tension t (cable law) and a constant `preload` pulling
the load away from the drum (a hanging weight, say) that keeps the cable taut:

    load_mass y'' = preload - t           (load_mass = inf: clamped, y fixed)

load_mass = 0 means no load at all: the free drum, the paper's m = m0.  For a rigid
cable the paper's effective mass is m = m0 + load_mass.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from cdpr.description import ActuatorSpec
from sim_bus.plant.config import PlantConfig
from sim_bus.plant.encoder import Encoders
from sim_bus.plant.winch import Winches

Array = NDArray[np.float64]

OUTPUTS = ("length", "rate", "load_position", "tension", "force")


class SingleActuatorRig:
    """One actuator (m0, k0, force_max of `actuator`, e.g. ``robot.actuators[k]``) with a
    cable `cable_length` long (m, drum exit to load) to a passive mass `load_mass` (kg;
    0: none, inf: clamped).  Starts at rest in equilibrium: tension = preload (against
    the clamp when clamped), command = -preload."""

    def __init__(
        self,
        actuator: ActuatorSpec,
        load_mass: float,
        config: PlantConfig | None = None,
        cable_length: float = 2.0,
        preload: float = 100.0,
    ) -> None:
        if not load_mass >= 0.0:
            raise ValueError(f"load_mass must be >= 0 (inf: clamped), got {load_mass}")
        if preload < 0.0 or not math.isfinite(preload):
            raise ValueError(f"preload must be a finite force >= 0, got {preload}")
        if not 0.0 < cable_length < math.inf:
            raise ValueError(f"cable_length must be a positive length, got {cable_length}")
        self.config = config = config or PlantConfig()
        self.load_mass = float(load_mass)
        self.preload = float(preload) if load_mass > 0.0 else 0.0
        self.cable_length = float(cable_length)
        self.winches = Winches([actuator.m0], [actuator.k0], [actuator.force_max], config)
        self.encoders = Encoders(config.encoder, 1, config.step, np.random.default_rng(config.seed))
        self._h = config.substep
        self._steps = 0
        self.time = 0.0
        self.reset()

    def reset(self) -> None:
        """Back to the equilibrium at rest, time 0."""
        self.load_position = self.cable_length
        self.load_velocity = 0.0
        self.winches.hold([self.cable_length], [self.preload], [0.0])
        self._rest_length = self.winches.lengths[0]
        self.encoders.reset(self.winches.lengths, self.winches.rates)
        self._steps = 0
        self.time = 0.0

    @property
    def equilibrium(self) -> dict[str, float]:
        """The operating point of linear_system(): the outputs at rest, and the command."""
        return {
            "length": self._rest_length,
            "rate": 0.0,
            "load_position": self.cable_length,
            "tension": self.preload,
            "force": -self.preload,
            "command": -self.preload,
        }

    def set_commands(self, commands: ArrayLike) -> None:
        """The force command (N), one value, held and saturated like the robot's."""
        self.winches.set_commands(np.asarray(commands, dtype=float).reshape(-1).tolist())

    def set_brake(self, k: int | None, engaged: bool) -> None:
        """Engage or release the holding brake (k: 0 or None, as sim_bus.plant.Plant)."""
        self.winches.set_brake(_only(k), engaged)

    def set_drive_enabled(self, k: int | None, enabled: bool) -> None:
        """Enable or disable the drive (k: 0 or None); disabled: no torque, no back-EMF."""
        self.winches.set_enabled(_only(k), enabled)

    def break_cable(self, k: int) -> None:
        """The cable snaps (k: 0): from now on it carries nothing."""
        self.winches.broken[_only(k)] = True

    def step(self) -> None:
        """Advance one plant step (config.step) in config.substeps substeps."""
        h = self._h
        movable = 0.0 < self.load_mass < math.inf
        for _ in range(self.config.substeps):
            tensions, wrench = self._pull()
            if movable:
                self.load_velocity += h * (self.preload + wrench[0]) / self.load_mass
                self.load_position += h * self.load_velocity
            self.winches.advance(tensions)
        self._steps += 1
        self.time = self._steps * self.config.step
        self.encoders.sample(self.winches.lengths)

    def _pull(self) -> tuple[list[float], tuple[float, ...]]:
        """Tension and the force on the load (along +y) now; nothing without a load."""
        if self.load_mass == 0.0:
            return [0.0], (0.0,)
        row = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.load_position)
        return self.winches.pull(row, (self.load_velocity, 0.0, 0.0, 0.0, 0.0, 0.0))

    def measure(self, ahead: float = 0.0) -> tuple[Array, Array]:
        """(length, rate) as the drive reports them, arrays of one element; `ahead`:
        Encoders.read."""
        return self.encoders.read(ahead)

    @property
    def commands(self) -> Array:
        """The held, saturated command."""
        return np.array(self.winches.commands)

    def snapshot(self) -> dict[str, list[float]]:
        """The true state for a recording (tuning.lockstep)."""
        w = self.winches
        return {
            "lengths": list(w.lengths),
            "rates": list(w.rates),
            "load_position": [self.load_position],
            "load_velocity": [self.load_velocity],
            "tensions": self._pull()[0],
            "forces": w.forces(),
        }

    def linear_system(self) -> signal.StateSpace:
        """The rig linearised at its equilibrium (friction: viscous part only), as
        deviations: input δf_c, outputs δ(length, rate, load_position, tension, force)
        in the order of OUTPUTS.  States: actuator (its order), l, l', then y, y' for
        a movable load."""
        w = self.winches
        model = w.models[0]
        n_a = model.order
        l0 = self.equilibrium["length"]
        y0 = self.cable_length
        EA, D = w.stiffness, w.damping
        loaded = self.load_mass > 0.0
        movable = loaded and math.isfinite(self.load_mass)
        n = n_a + 2 + (2 if movable else 0)
        il, iv, iy, iyd = n_a, n_a + 1, n_a + 2, n_a + 3
        # tension row dt = T x (input does not enter): dt/dy, dt/dl, dt/dy', dt/dl'
        T = np.zeros(n)
        if loaded:
            T[il] = -EA * y0 / l0**2
            T[iv] = -D / l0
            if movable:
                T[iy] = EA / l0
                T[iyd] = D / l0
        # inner force f_in = Cf x + Df u
        Cf = np.zeros(n)
        Cf[:n_a] = model.C[0]
        Df = float(model.D[0, 0])
        A = np.zeros((n, n))
        B = np.zeros((n, 1))
        A[:n_a, :n_a] = model.A
        A[:n_a, iv] = model.B[:, 1]
        B[:n_a, 0] = model.B[:, 0]
        A[il, iv] = 1.0
        M = w.mass[0]
        drag = model.q0 + self.config.friction.viscous
        accel = (Cf + T) / M  # l'' = (f_in - drag l' + t) / M
        accel[iv] -= drag / M
        A[iv] = accel
        B[iv, 0] = Df / M
        if movable:
            A[iy, iyd] = 1.0
            A[iyd] = -T / self.load_mass
        C = np.zeros((len(OUTPUTS), n))
        Dm = np.zeros((len(OUTPUTS), 1))
        C[0, il] = 1.0
        C[1, iv] = 1.0
        if movable:
            C[2, iy] = 1.0
        C[3] = T
        # f = f_in - q0 l' - q1 l''
        C[4] = Cf - model.q1 * A[iv]
        C[4, iv] -= model.q0
        Dm[4, 0] = Df - model.q1 * B[iv, 0]
        return signal.StateSpace(A, B, C, Dm)


def _only(k: int | None) -> int:
    """The rig's one winch: index 0 (None: all, the same one)."""
    if k not in (0, None):
        raise IndexError(f"the single-actuator rig has one winch (0), not {k}")
    return 0
