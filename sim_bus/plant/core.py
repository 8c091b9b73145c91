"""The robot plant: a rigid platform on elastic unilateral cables spooled by winches.

State: the platform's centre of mass position x_c and velocity v_c (world), its
orientation q (platform -> world) and body-frame angular velocity ω_b, and the winches
(sim_bus.plant.winch).  Each substep h, with the cable geometry from cdpr (the same
lengths and Jacobian rows [u_k, r_k x u_k] as the controller's model, pulleys included):

    L_k, u_k, r_k x u_k    at the reference point p = x_c - R c_b
    L'_k = Λ_k φ           with the mixed twist φ = (v_c - ω x R c_b, ω), ω = R ω_b
    t_k                    cable law of the winches
    F = -Σ t_k u_k + F_d,  τ_p = -Σ t_k (r_k x u_k) + τ_d     (the -Λᵀ t of DESIGN §3)
    m v_c' = F + m g,      I_b ω_b' = R^T (τ_p - R c_b x F) - ω_b x I_b ω_b

then semi-implicit (symplectic) Euler: velocities first, then x_c += h v_c and
q <- exp(h ω) q with the new velocities; the winches advance under the same t_k.
Keeping the state at the centre of mass with Euler's equations in the body frame
avoids solving the 6 x 6 mass matrix every substep.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr import Pose, Robot
from cdpr.so3 import quat_to_r9, rotate_quat_by_rotvec
from sim_bus.plant.config import DisturbanceConfig, PlantConfig
from sim_bus.plant.encoder import Encoders
from sim_bus.plant.fixture import Fixture
from sim_bus.plant.statics import equilibrium_tensions
from sim_bus.plant.winch import Winches

Array = NDArray[np.float64]
Disturbance = Callable[[float], Sequence[float]]


class Plant:
    """Simulated CDPR.  ``Plant(robot, config)`` simulates ``config.mismatch`` applied
    to the controller's model `robot` (available as ``plant.robot``), starting at rest
    at its home pose in static equilibrium (equilibrium_tensions).  A `disturbance`
    function of time returning a wrench (force, torque about p; world frame) overrides
    ``config.disturbance``.
    """

    def __init__(
        self,
        robot: Robot,
        config: PlantConfig | None = None,
        disturbance: Disturbance | None = None,
    ) -> None:
        self.config = config = config or PlantConfig()
        mismatch_seed, encoder_seed = np.random.SeedSequence(config.seed).spawn(2)
        self.model = robot
        self.robot = true = config.mismatch.apply(robot, np.random.default_rng(mismatch_seed))
        self.n = true.n_cables
        self.winches = Winches(true.m0, true.k0, true.force_max, config)
        self.encoders = Encoders(
            config.encoder, self.n, config.step, np.random.default_rng(encoder_seed)
        )
        platform = true.platform
        self._mass = platform.mass
        self._gravity = platform.gravity
        self._cb = platform.center_of_mass
        self._inertia = tuple(platform.inertia.reshape(9).tolist())
        self._inertia_inv = tuple(np.linalg.inv(platform.inertia).reshape(9).tolist())
        self._geometry = true.geometry
        self._disturbance = disturbance or _constant_or_step(config.disturbance)
        self._h = config.substep
        self._steps = 0
        self.time = 0.0
        self._fixture: Fixture | None = None
        self.reset(true.home, equilibrium_tensions(true, true.home))
        if config.fixture is not None:
            self._rest_on_fixture()

    # -- set-up and inputs ------------------------------------------------------------

    def reset(
        self, pose: Pose, tensions: ArrayLike | None = None, twist: ArrayLike | None = None
    ) -> None:
        """Place the platform at `pose` moving with `twist` (mixed, default 0), the cables
        carrying `tensions` (default equilibrium_tensions of the true robot) and the
        actuators in steady state producing them; brakes off, no faults, time 0.
        At rest with equilibrium tensions this is a static equilibrium."""
        if tensions is None:
            tensions = equilibrium_tensions(self.robot, pose)
        phi = [0.0] * 6 if twist is None else np.asarray(twist, dtype=float).reshape(6).tolist()
        q = tuple(pose.quaternion.tolist())
        R = quat_to_r9(*q)
        cx, cy, cz = _rotate(R, self._cb)
        wx, wy, wz = phi[3:]
        px, py, pz = pose.position.tolist()
        self._q = q
        self._xc = [px + cx, py + cy, pz + cz]
        self._vc = [
            phi[0] + wy * cz - wz * cy,
            phi[1] + wz * cx - wx * cz,
            phi[2] + wx * cy - wy * cx,
        ]
        self._wb = list(_rotate_t(R, (wx, wy, wz)))
        table = self._table(pose.position_tuple, q)
        rows = list(zip(*[iter(table)] * 7, strict=False))
        rates = [sum(a * b for a, b in zip(row[:6], phi, strict=True)) for row in rows]
        self.winches.hold(table[6::7], np.asarray(tensions, float).tolist(), rates)
        self.encoders.reset(self.winches.lengths, self.winches.rates)
        self._steps = 0
        self.time = 0.0
        self._cache = None

    def set_commands(self, commands: ArrayLike) -> None:
        """Force commands f_c (N, along +l), held until the next call, saturated at
        each drive's force_max; ValueError on a wrong count or a non-finite value."""
        self.winches.set_commands(np.asarray(commands, dtype=float).reshape(-1).tolist())

    def set_brake(self, k: int | None, engaged: bool) -> None:
        """Engage or release the holding brake of winch k (None: all winches)."""
        for i in range(self.n) if k is None else (k,):
            self.winches.set_brake(i, engaged)
        self._cache = None

    def set_drive_enabled(self, k: int | None, enabled: bool) -> None:
        """Enable or disable drive k (None: all); disabled: no torque, no back-EMF."""
        for i in range(self.n) if k is None else (k,):
            self.winches.set_enabled(i, enabled)

    def release(self, k: int) -> None:
        """Let cable k go: drive disabled and brake off, so the drum free-wheels and pays
        out under the tension until the cable is slack."""
        self.set_drive_enabled(k, False)
        self.set_brake(k, False)

    def break_cable(self, k: int) -> None:
        """Cable k snaps: from now on it carries no tension."""
        self.winches.broken[k] = True
        self._cache = None

    def _rest_on_fixture(self) -> None:
        """config.fixture: the platform at rest on the fixture (sunk by its weight over
        the contact's stiffness), every cable slack_m longer than taut, nothing commanded."""
        fixture = self.config.fixture
        assert fixture is not None
        pose = fixture.resting_pose(self.robot)
        self.reset(pose, np.zeros(self.n))
        self._fixture = Fixture(fixture, pose)
        winches = self.winches
        for k, slack in enumerate(fixture.slack_for(self.n)):
            winches.lengths[k] += slack
        winches.commands = [0.0] * self.n
        for k in range(self.n):
            winches.states[k] = [0.0] * winches.order
        weight = [self._mass * g / fixture.stiffness for g in self._gravity]
        self._xc = [x + w for x, w in zip(self._xc, weight, strict=True)]
        self.encoders.reset(winches.lengths, winches.rates)

    # -- time -----------------------------------------------------------------------

    def step(self) -> None:
        """Advance one plant step (config.step) in config.substeps substeps."""
        t0 = self._steps * self.config.step
        for i in range(self.config.substeps):
            self._substep(t0 + i * self._h)
        self._steps += 1
        self.time = self._steps * self.config.step
        self.encoders.sample(self.winches.lengths)

    def advance(self, duration: float) -> None:
        """Advance by `duration` seconds, a whole number of plant steps."""
        steps = round(duration / self.config.step)
        if abs(steps * self.config.step - duration) > 1e-9 * max(1.0, duration):
            raise ValueError(f"{duration} s is not a whole number of {self.config.step} s steps")
        for _ in range(steps):
            self.step()

    def _substep(self, t: float) -> None:
        cache = self._cache
        R, c, _, tensions, wrench = cache if cache is not None else self._forces(t)
        self._cache = None
        h = self._h
        m = self._mass
        fx, fy, fz, tx, ty, tz = wrench
        gx, gy, gz = self._gravity
        vc = self._vc
        vc[0] += h * (fx / m + gx)
        vc[1] += h * (fy / m + gy)
        vc[2] += h * (fz / m + gz)
        # Euler's equations in the body frame, torque about the centre of mass
        cx, cy, cz = c
        tx -= cy * fz - cz * fy
        ty -= cz * fx - cx * fz
        tz -= cx * fy - cy * fx
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
        bx = r00 * tx + r10 * ty + r20 * tz  # R^T τ
        by = r01 * tx + r11 * ty + r21 * tz
        bz = r02 * tx + r12 * ty + r22 * tz
        wx, wy, wz = self._wb
        i00, i01, i02, i10, i11, i12, i20, i21, i22 = self._inertia
        hx = i00 * wx + i01 * wy + i02 * wz
        hy = i10 * wx + i11 * wy + i12 * wz
        hz = i20 * wx + i21 * wy + i22 * wz
        bx -= wy * hz - wz * hy
        by -= wz * hx - wx * hz
        bz -= wx * hy - wy * hx
        j00, j01, j02, j10, j11, j12, j20, j21, j22 = self._inertia_inv
        wx += h * (j00 * bx + j01 * by + j02 * bz)
        wy += h * (j10 * bx + j11 * by + j12 * bz)
        wz += h * (j20 * bx + j21 * by + j22 * bz)
        self._wb = [wx, wy, wz]
        xc = self._xc
        xc[0] += h * vc[0]
        xc[1] += h * vc[1]
        xc[2] += h * vc[2]
        if not math.isfinite(wx * wx + wy * wy + wz * wz + vc[0] ** 2 + vc[1] ** 2 + vc[2] ** 2):
            raise FloatingPointError(
                f"the plant diverged at t = {t:.6g} s: the step {h:g} s is too long for "
                "the cable stiffness (or the state left the workspace)"
            )
        self._q = rotate_quat_by_rotvec(
            self._q,
            h * (r00 * wx + r01 * wy + r02 * wz),
            h * (r10 * wx + r11 * wy + r12 * wz),
            h * (r20 * wx + r21 * wy + r22 * wz),
        )
        self.winches.advance(tensions)

    def _table(self, position: tuple, q: tuple) -> list[float]:
        """Per cable [u, r x u, l] (stride 7, flat) at a position and unit quaternion."""
        table, lengths = self._geometry.table(position, q)
        table[:, 6] = lengths
        return table.ravel().tolist()

    def _forces(self, t: float | None = None) -> tuple:
        """Geometry, tensions and the non-gravity wrench (force, torque about p) now."""
        R = r00, r01, r02, r10, r11, r12, r20, r21, r22 = quat_to_r9(*self._q)
        bx, by, bz = self._cb
        c = cx, cy, cz = (
            r00 * bx + r01 * by + r02 * bz,
            r10 * bx + r11 * by + r12 * bz,
            r20 * bx + r21 * by + r22 * bz,
        )
        bx, by, bz = self._wb
        wx = r00 * bx + r01 * by + r02 * bz
        wy = r10 * bx + r11 * by + r12 * bz
        wz = r20 * bx + r21 * by + r22 * bz
        xc = self._xc
        vc = self._vc
        vx = vc[0] - (wy * cz - wz * cy)
        vy = vc[1] - (wz * cx - wx * cz)
        vz = vc[2] - (wx * cy - wy * cx)
        position = (xc[0] - cx, xc[1] - cy, xc[2] - cz)
        table = self._table(position, self._q)
        tensions, (fx, fy, fz, tx, ty, tz) = self.winches.pull(table, (vx, vy, vz, wx, wy, wz))
        if self._disturbance is not None:
            dfx, dfy, dfz, dtx, dty, dtz = self._disturbance(self.time if t is None else t)
            fx += dfx
            fy += dfy
            fz += dfz
            tx += dtx
            ty += dty
            tz += dtz
        if self._fixture is not None:
            contact = self._fixture.wrench(position, self._q, (vx, vy, vz), (wx, wy, wz))
            if contact is not None:
                fx, fy, fz, tx, ty, tz = (a + b for a, b in zip(
                    (fx, fy, fz, tx, ty, tz), contact, strict=True))  # fmt: skip
        self._cache = (R, c, table, tensions, (fx, fy, fz, tx, ty, tz))
        return self._cache

    # -- measurement and true state ---------------------------------------------------

    def measure(self, ahead: float = 0.0) -> tuple[Array, Array]:
        """(lengths in m, rates in m/s) as the drives report them (config.encoder), or
        `ahead` s after the last step (Encoders.read)."""
        return self.encoders.read(ahead)

    @property
    def pose(self) -> Pose:
        """True platform pose (reference point p)."""
        return Pose._from_unit(self._reference_state()[0], self._q)

    @property
    def twist(self) -> Array:
        """True twist φ = (v, ω) in mixed coordinates (DESIGN §3)."""
        return np.array(self._reference_state()[1])

    def _reference_state(self) -> tuple[list[float], list[float]]:
        """p and φ = (v, ω) of the reference point, from the centre-of-mass state."""
        R = quat_to_r9(*self._q)
        cx, cy, cz = _rotate(R, self._cb)
        wx, wy, wz = _rotate(R, self._wb)
        xc, vc = self._xc, self._vc
        position = [xc[0] - cx, xc[1] - cy, xc[2] - cz]
        twist = [
            vc[0] - (wy * cz - wz * cy),
            vc[1] - (wz * cx - wx * cz),
            vc[2] - (wx * cy - wy * cx),
            wx,
            wy,
            wz,
        ]
        return position, twist

    def snapshot(self) -> dict[str, Sequence[float]]:
        """The true state now, as plain lists, for a recording (tuning.lockstep)."""
        position, twist = self._reference_state()
        _, _, table, tensions, _ = self._current()
        return {
            "position": position,
            "quaternion": self._q,
            "twist": twist,
            "lengths": list(self.winches.lengths),
            "rates": list(self.winches.rates),
            "cable_lengths": table[6::7],
            "tensions": list(tensions),
            "forces": self.winches.forces(),
        }

    @property
    def tensions(self) -> Array:
        """True cable tensions now (N)."""
        return np.array(self._current()[3])

    @property
    def cable_lengths(self) -> Array:
        """Geometric cable lengths L now (m), stretch included."""
        return np.array(self._current()[2][6::7])

    @property
    def drum_lengths(self) -> Array:
        """Unstretched cable paid out by each drum, l (m): what an ideal encoder reads."""
        return np.array(self.winches.lengths)

    @property
    def drum_rates(self) -> Array:
        """l' (m/s)."""
        return np.array(self.winches.rates)

    @property
    def forces(self) -> Array:
        """Actual actuator forces f (N, along +l)."""
        return np.array(self.winches.forces())

    @property
    def commands(self) -> Array:
        """The held, saturated force commands (N)."""
        return np.array(self.winches.commands)

    def energy(self) -> float:
        """Mechanical energy (J): platform and drum kinetic energy, gravity potential
        (zero at z = 0 for g along -z) and cable strain energy.  Actuator forces and
        the disturbance do work on it from outside."""
        m = self._mass
        vc = self._vc
        wx, wy, wz = self._wb
        i00, i01, i02, i10, i11, i12, i20, i21, i22 = self._inertia
        rot = wx * (i00 * wx + i01 * wy + i02 * wz) + wy * (i10 * wx + i11 * wy + i12 * wz)
        rot += wz * (i20 * wx + i21 * wy + i22 * wz)
        kinetic = 0.5 * m * (vc[0] ** 2 + vc[1] ** 2 + vc[2] ** 2) + 0.5 * rot
        potential = -m * sum(g * x for g, x in zip(self._gravity, self._xc, strict=True))
        return kinetic + potential + self.winches.energy(self._current()[2][6::7])

    def _current(self) -> tuple:
        return self._cache or self._forces()


def _rotate(R: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = v
    return (
        R[0] * x + R[1] * y + R[2] * z,
        R[3] * x + R[4] * y + R[5] * z,
        R[6] * x + R[7] * y + R[8] * z,
    )


def _rotate_t(R: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    x, y, z = v
    return (
        R[0] * x + R[3] * y + R[6] * z,
        R[1] * x + R[4] * y + R[7] * z,
        R[2] * x + R[5] * y + R[8] * z,
    )


def _constant_or_step(config: DisturbanceConfig) -> Disturbance | None:
    """The configured wrench as a function of time; None when it is zero."""
    if not any(config.wrench):
        return None
    wrench, zero = tuple(config.wrench), (0.0,) * 6
    start, end = config.start, config.end
    return lambda t: wrench if start <= t < end else zero
