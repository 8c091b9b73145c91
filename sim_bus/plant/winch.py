"""Winches: drums, their actuators and the elastic cables they spool (scalar hot path).

Shared by the robot plant and the single-actuator rig, so the rig tunes exactly the
actuator the robot has.  Per cable k, over one substep h (semi-implicit Euler):

    f_in        inner actuator force (sim_bus.plant.actuator), from its state and f_c
    M l''       = f_in - (q0 + b) l' + t - F_c sgn(l'),  M = m0 + q1,  b viscous friction
    t           = max(0, EA ε + D ε'),  ε = (L - l) / l, while L > l; else 0 (slack)

with the damping terms and the Coulomb friction taken implicitly (a drum whose free
velocity change is within the friction impulse sticks), then l += h l', then the
actuator state is advanced by its exact discretisation with the new l'.  A braked drum
is locked (l' = 0); a disabled drive produces no force and no back-EMF; a broken cable
carries nothing.  Commands are held (zero-order hold) and saturated at +-force_max.
"""

from __future__ import annotations

import math
import operator
import random
from collections.abc import Sequence

from sim_bus.plant.config import PlantConfig


class Winches:
    """n winches in cable-length coordinates (m, N); lists of floats, not arrays."""

    def __init__(
        self,
        m0: Sequence[float],
        k0: Sequence[float],
        force_max: Sequence[float],
        config: PlantConfig,
    ) -> None:
        self.n = n = len(m0)
        self.h = h = config.substep
        self.stiffness = config.cable.stiffness
        self.damping = config.cable.damping
        self.models = [config.actuator.model(float(k)) for k in k0]
        self.order = self.models[0].order
        self.mass = [float(m) + a.q1 for m, a in zip(m0, self.models, strict=True)]
        self.force_max = [float(f) for f in force_max]
        self._viscous = config.friction.viscous
        self._force_noise = config.force_noise
        self._rng = random.Random(config.seed)
        self._coulomb = config.friction.coulomb
        # per winch (Ad, Bd f_c column, Bd l' column, C, D f_c): scalars for the default
        # first-order model, else nested lists
        self._discrete = []
        for model in self.models:
            Ad, Bd, C, D = model.discretise(h)
            matrices = (Ad, Bd[:, 0], Bd[:, 1], C[0])
            if self.order == 1:
                self._discrete.append((*(float(a.flat[0]) for a in matrices), float(D[0, 0])))
            else:
                self._discrete.append((*(a.tolist() for a in matrices), float(D[0, 0])))
        self.lengths = [0.0] * n  # unstretched cable paid out, l (m)
        self.rates = [0.0] * n  # l' (m/s)
        self.accelerations = [0.0] * n  # l'' over the last substep (m/s^2)
        self.states = [[0.0] * self.order for _ in range(n)]
        self.commands = [0.0] * n  # held, saturated
        self.braked = [False] * n
        self.disabled = [False] * n
        self.broken = [False] * n
        self._drums: list[tuple[float, float, float]] = []  # see _prepare_drums
        self._prepare_drums()

    # -- state ----------------------------------------------------------------------

    def hold(
        self, geometric: Sequence[float], tensions: Sequence[float], rates: Sequence[float]
    ) -> None:
        """Cables that carry `tensions` at geometric lengths L moving at `rates`, and
        actuators in steady state producing f = -t: commands f_c = -t + k_0 l' (the
        paper's back-EMF feed-forward f_b).  Brakes off, drives on, cables whole."""
        EA = self.stiffness
        self.braked = [False] * self.n
        self.disabled = [False] * self.n
        self.broken = [False] * self.n
        self._prepare_drums()
        for k, (L, t, v) in enumerate(zip(geometric, tensions, rates, strict=True)):
            if t < 0.0:
                raise ValueError(f"cable {k}: tension {t} N is negative")
            self.lengths[k] = L * EA / (EA + t)
            self.rates[k] = v
            model = self.models[k]
            command = -t + model.back_emf * v
            self.commands[k] = command
            self.states[k] = model.steady_state(command, v).tolist()
            self.accelerations[k] = 0.0

    def set_commands(self, commands: Sequence[float]) -> None:
        """Hold new force commands (N), saturated at the drives' limits."""
        if len(commands) != self.n:
            raise ValueError(f"expected {self.n} commands, got {len(commands)}")
        out = []
        for k, (f, lim) in enumerate(zip(commands, self.force_max, strict=True)):
            f = float(f)
            if not math.isfinite(f):
                raise ValueError(f"command {k} is not finite: {f}")
            if self._force_noise:
                f *= 1.0 + self._rng.gauss(0.0, self._force_noise)
            out.append(lim if f > lim else -lim if f < -lim else f)
        self.commands = out

    def set_brake(self, k: int, engaged: bool) -> None:
        """Engage (lock the drum at once) or release winch k's holding brake."""
        self.braked[k] = engaged
        if engaged:
            self.rates[k] = 0.0

    def set_enabled(self, k: int, enabled: bool) -> None:
        """Enable or disable drive k; a disabled drive produces no force and no back-EMF.
        Either way its electrical state restarts from zero."""
        self.disabled[k] = not enabled
        self.states[k] = [0.0] * self.order
        self._prepare_drums()

    def _prepare_drums(self) -> None:
        """Per drum (h / M, Coulomb velocity impulse h F_c / M, 1 / (1 + h drag / M)) with
        drag = q0 + viscous (viscous alone for a disabled drive)."""
        h = self.h
        self._drums = [
            (
                h / M,
                h * self._coulomb / M,
                1.0 / (1.0 + h * (self._viscous + (0.0 if off else m.q0)) / M),
            )
            for M, m, off in zip(self.mass, self.models, self.disabled, strict=True)
        ]

    # -- physics --------------------------------------------------------------------

    def pull(
        self, table: Sequence[float], twist: Sequence[float]
    ) -> tuple[list[float], tuple[float, float, float, float, float, float]]:
        """Cable tensions t (N) and the wrench -Λᵀ t they exert on the body, given the
        flat table [u_k, r_k x u_k, L_k] (stride 7, as cdpr's geometry.evaluate returns
        it) and the body's twist φ, which give L'_k = Λ_k φ."""
        EA = self.stiffness
        D = self.damping
        vx, vy, vz, wx, wy, wz = twist
        fx = fy = fz = tx = ty = tz = 0.0
        tensions = []
        rows = zip(*[iter(table)] * 7, strict=True)
        for (ux, uy, uz, mx, my, mz, L), ell, v, broken in zip(
            rows, self.lengths, self.rates, self.broken, strict=True
        ):
            stretch = L - ell
            if stretch <= 0.0 or broken:
                tensions.append(0.0)
                continue
            rate = ux * vx + uy * vy + uz * vz + mx * wx + my * wy + mz * wz
            t = (EA * stretch + D * (rate - v)) / ell
            if t <= 0.0:
                tensions.append(0.0)
                continue
            tensions.append(t)
            fx -= t * ux
            fy -= t * uy
            fz -= t * uz
            tx -= t * mx
            ty -= t * my
            tz -= t * mz
        return tensions, (fx, fy, fz, tx, ty, tz)

    def forces(self) -> list[float]:
        """Actual actuator forces f = f_in - q0 l' - q1 l'' (N)."""
        out = []
        for model, x, fc, v, a, (_, _, _, C, Dc), off in zip(
            self.models, self.states, self.commands, self.rates, self.accelerations,
            self._discrete, self.disabled, strict=True,
        ):  # fmt: skip
            if off:
                out.append(-model.q1 * a)
                continue
            f_in = Dc * fc + (C * x[0] if self.order == 1 else sum(map(operator.mul, C, x)))
            out.append(f_in - model.q0 * v - model.q1 * a)
        return out

    def advance(self, tensions: Sequence[float]) -> None:
        """One substep of the drums and actuators under the given cable tensions."""
        h = self.h
        inv_h = 1.0 / h
        first_order = self.order == 1
        lengths, rates, accels = self.lengths, self.rates, self.accelerations
        for k, (t, fc, x, (h_m, stick, damp), (Ad, Bf, Bv, C, Dc), braked, off) in enumerate(
            zip(
                tensions, self.commands, self.states, self._drums, self._discrete,
                self.braked, self.disabled, strict=True,
            )
        ):  # fmt: skip
            if off:
                fc = f_in = 0.0
            elif first_order:  # the default lag, scalar coefficients
                f_in = Dc * fc + C * x[0]
            else:
                f_in = Dc * fc
                for c, xi in zip(C, x, strict=True):
                    f_in += c * xi
            v = rates[k]
            if braked:
                v_new = 0.0
            else:
                v_free = v + h_m * (f_in + t)
                if -stick <= v_free <= stick:
                    v_new = 0.0
                else:
                    v_new = (v_free - (stick if v_free > 0.0 else -stick)) * damp
                lengths[k] += h * v_new
            accels[k] = (v_new - v) * inv_h
            rates[k] = v_new
            if off:
                continue
            if first_order:
                x[0] = Ad * x[0] + Bf * fc + Bv * v_new
            else:
                x[:] = [
                    sum(a * xj for a, xj in zip(row, x, strict=True)) + bf * fc + bv * v_new
                    for row, bf, bv in zip(Ad, Bf, Bv, strict=True)
                ]

    def energy(self, geometric: Sequence[float]) -> float:
        """Drum kinetic energy plus cable strain energy EA (L - l)^2 / (2 l) (J)."""
        EA = self.stiffness
        e = 0.0
        for L, ell, v, M, broken in zip(
            geometric, self.lengths, self.rates, self.mass, self.broken, strict=True
        ):
            e += 0.5 * M * v * v
            if ell < L and not broken:
                e += 0.5 * EA * (L - ell) ** 2 / ell
        return e
