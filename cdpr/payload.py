"""The platform's mass, centre of mass and, where rotation excites it, inertia,
identified from the wrench the cables exert and the motion (payload
adaptation; DESIGN §15 step 6).

The platform's dynamics are linear in its ten inertial parameters.  With h = m c_b (the
first moment, platform frame), c = R c_b, G = a - g (a = p'' the reference point's
acceleration), and I_p = R I_pb R^T the inertia about p, the platform's wrench about p is

    force  = m G + ([w']x + [w]x[w]x) R h
    torque = (R h) x G + R (I_pb w_b' + w_b x (I_pb w_b))     (w_b = R^T w)

so  Y(R, w, w', a) x = y  with x = (m, h / L, I_pb / L_I^2) (I_pb's six entries xx, xy,
xz, yy, yz, zz), the torque rows divided by L (LENGTH): every parameter is a mass, every
entry of Y an acceleration, and with L_I^2 = L x 1 m (INERTIA_LENGTH) an angular
acceleration of 1 rad/s^2 is an entry of 1 m/s^2: the inertia is identified in the
directions an angular acceleration of about 1 rad/s^2 RMS excites (EXCITED), and stays
the robot file's (about the centre of mass) under pure translation.  The wrench y is
what the cables exert on the platform at a measurement instant t_k, from what the drives
did then, not what the cycle planned: per cable the tension t = f - k0 l' - m0 l'', with f
the drive's force as its mean over the period centred on t_k (`drive_force_weights`: the
commands, held from `latency` after their measurement, through the drive's first-order
lag drive_lag; the force ripples within each cycle as its command lands, and its value
at t_k depended on where the latency puts t_k in that ripple: the inertia's z -0.4 %
without latency, +2.5 % at 0.5 ms, +4.4 % at 1 ms), Assumption 1's back-EMF lagging as
well (k0 (l' - drive_lag l'')), l' the drums' rates (the drives report means over the
period before the measurement: l'(t_k) is the mean of this and the next cycle's) and l''
the second difference of the drums' lengths over SPAN cycles either side (a shorter span
is noisier with quantised lengths; the drums carry about three times the platform's
rotational inertia, so their share must be right): both ripple-free, and smooth enough
that their means are their values at t_k (a longer mean of the force, the triangle over
SPAN cycles that l'' is, was not: under ~300 N of internal force the tensions' curvature
while the platform turns read as 2.5 % on y), and y = Lambda(eta)^T t at the
measured pose moved by the stretch these tensions cause beyond the planned ones (which
forward kinematics applied), the strain following the tensions D / EA late (the robot
file's cable_damping: t - (D / EA) t', t' from the forces of the cycles either side;
without it reference8's 1 ms read as z +10 % at 0.7x the file's inertia, x -3 % at
1.5x).  The sample waits SPAN cycles for its data.  The motion is
the reference's at t_k: the true acceleration differs by the tracking error's, which
averages out over the window.  From the planned forces instead (the force lag, the
back-EMF of the reference's rates, the stretch of the planned tensions) the ~0.2 N m of
difference on reference8's EA 1e5 cables, under ~300 N of internal force, was taken for
inertia: the x and z diagonal off by up to a half (z +47 % at 0.7x the file's inertia).

Least squares with exponential forgetting (WINDOW) accumulates Y^T Y and Y^T y of every
SAMPLE_EVERY-th cycle; every SOLVE_EVERY cycles the estimate moves, with time constant
`time_constant`, towards the least-squares solution in the directions the data excite
(eigenvalues of the mean Y^T Y above EXCITED, i.e. an excitation of 1 m/s^2 RMS) and not
at all in the others, where the centre of mass and the inertia about it stay (a new mass
at the old centre of mass, with the old inertia about it); and only as far as the
solution lies beyond a dead zone (DEAD_ZONE of the mass: the regression's own errors,
~0.2 % at rest, or a mode ringing down, do not move the model; the integral action has
the rest).

At rest G = -g: the mass and the horizontal (world) components of R h are identified,
the vertical one is not (a centre of mass moved along gravity changes no static
wrench); tilting the platform or accelerating it sideways excites it.  The inertia
needs angular accelerations.  The model takes the estimate while it lies within the
configured limits (an inertia about the centre of mass whose diagonal lies within
inertia_scale_max of the file's either way, positive definite); an estimate beyond them
is a fault (`fault`: the daemon brakes), never the model.  Nothing moves while frozen.

`static_fit` is the same regression over a few poses held at rest (identify-payload):
mass and centre of mass with their standard deviations (at rest the inertia shows not).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dpotrs

from cdpr.control_spec import AdaptationSpec
from cdpr.dynamics import PlatformInertia
from cdpr.forward_kinematics import FKResult
from cdpr.pose import Pose, retract
from cdpr.robot import Robot
from cdpr.so3 import quat_to_r9
from cdpr.trajectory import Reference

Array = NDArray[np.float64]

LENGTH = 0.2  # m: the length scale between forces and torques (about a platform's size)
INERTIA_LENGTH = math.sqrt(LENGTH)  # m: 1 rad/s^2 on the inertia is 1 m/s^2 on the mass
PARAMETERS = 10  # m, h (3), I_pb (6)
_INERTIA_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # of I_pb, in x
WINDOW = 1.0  # s: forgetting time of the least-squares data
EXCITED = 1.0  # (m/s^2)^2: the least mean eigenvalue of Y^T Y of a direction identified
SAMPLE_EVERY = 4  # cycles between two samples taken in (~50 us each: not every cycle)
SOLVE_EVERY = 20  # cycles between two solutions (eigh ~20 us), between two samples
SPAN = 6  # cycles each side of a sample over which the drums' acceleration is taken
GAP = 0.5  # of a period: two cycles apart by a period +- more than this are not adjacent
FORGOTTEN = 1e-6  # of a command: what is left of it in the drive's force is neglected
UNSEEN = 1e-9  # an excited direction's inertia components, at most, when rotation is absent
DEAD_ZONE = 0.005  # of the file's mass: a smaller difference is left to the integral action
DEFAULT_MASS_RANGE = (0.8, 1.5)  # mass_min, mass_max as multiples of the file's mass


class PayloadLimits(NamedTuple):
    """What the estimate may take: mass in [mass_min, mass_max] kg, centre of mass within
    com_max m of the robot file's, the inertia's diagonal (about the centre of mass)
    within inertia_scale_max of the file's either way."""

    mass_min: float
    mass_max: float
    com_max: float
    inertia_scale_max: float


def payload_limits(robot: Robot, spec: AdaptationSpec) -> PayloadLimits:
    """The limits of `spec` for `robot` (defaults from its mass); ValueError naming the key
    when the robot file's own mass lies outside them."""
    mass = robot.platform.mass
    low, high = DEFAULT_MASS_RANGE
    limits = PayloadLimits(
        mass * low if spec.mass_min is None else spec.mass_min,
        mass * high if spec.mass_max is None else spec.mass_max,
        spec.com_max,
        spec.inertia_scale_max,
    )
    if not limits.mass_min <= mass <= limits.mass_max:
        key = "mass_min" if mass < limits.mass_min else "mass_max"
        raise ValueError(
            f"adaptation.{key}: the robot file's platform mass {mass:g} kg lies outside "
            f"[{limits.mass_min:g}, {limits.mass_max:g}] kg"
        )
    return limits


def regressor(
    pose: Pose,
    accel: Sequence[float],
    twist: Sequence[float],
    gravity: Sequence[float],
    wrench: Sequence[float],
) -> list[float]:
    """[Y | y] (6 x 11, row-major, 66 floats) for the platform at `pose` moving with
    `twist` and `accel` under `wrench` (world frame, about p): see the module docstring."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R = quat_to_r9(*pose.quaternion_tuple)
    gx = accel[0] - gravity[0]
    gy = accel[1] - gravity[1]
    gz = accel[2] - gravity[2]
    wx, wy, wz = twist[3], twist[4], twist[5]
    dx, dy, dz = accel[3], accel[4], accel[5]
    # K = [w']x + [w]x[w]x = [w']x + w w^T - |w|^2 I
    ww = wx * wx + wy * wy + wz * wz
    k = (
        wx * wx - ww, wx * wy - dz, wx * wz + dy,
        wy * wx + dz, wy * wy - ww, wy * wz - dx,
        wz * wx - dy, wz * wy + dx, wz * wz - ww,
    )  # fmt: skip
    cols = ((r00, r10, r20), (r01, r11, r21), (r02, r12, r22))  # R's columns
    force_h = [
        [LENGTH * (k[3 * i] * c[0] + k[3 * i + 1] * c[1] + k[3 * i + 2] * c[2]) for c in cols]
        for i in range(3)
    ]
    # (R x) x G for x the unit vectors: each column of R crossed with G
    torque_h = [
        [c[1] * gz - c[2] * gy for c in cols],
        [c[2] * gx - c[0] * gz for c in cols],
        [c[0] * gy - c[1] * gx for c in cols],
    ]
    # the inertia's torque R (I_pb bd + bw x (I_pb bw)), per entry of I_pb (bw = R^T w,
    # bd = R^T w'): I_pb v = E(v) (xx, xy, xz, yy, yz, zz)
    bw = (r00 * wx + r10 * wy + r20 * wz, r01 * wx + r11 * wy + r21 * wz,
          r02 * wx + r12 * wy + r22 * wz)  # fmt: skip
    bd = (r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz,
          r02 * dx + r12 * dy + r22 * dz)  # fmt: skip
    scale = INERTIA_LENGTH * INERTIA_LENGTH / LENGTH
    torque_i: list[list[float]] = [[], [], []]
    for i, j in _INERTIA_ENTRIES:
        # E(v)'s column for entry (i, j): v_j at row i and v_i at row j
        ed, ew = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        ed[i] += bd[j]
        ew[i] += bw[j]
        if i != j:
            ed[j] += bd[i]
            ew[j] += bw[i]
        body = (
            ed[0] + bw[1] * ew[2] - bw[2] * ew[1],
            ed[1] + bw[2] * ew[0] - bw[0] * ew[2],
            ed[2] + bw[0] * ew[1] - bw[1] * ew[0],
        )
        for row in range(3):
            torque_i[row].append(
                scale * (R[3 * row] * body[0] + R[3 * row + 1] * body[1] + R[3 * row + 2] * body[2])
            )
    g = (gx, gy, gz)
    zero = (0.0,) * 6
    rows: list[float] = []
    for i in range(3):
        rows += (g[i], *force_h[i], *zero, wrench[i])
    for i in range(3):
        rows += (0.0, *torque_h[i], *torque_i[i], wrench[3 + i] / LENGTH)
    return rows


def parameters(
    mass: float, center_of_mass: Sequence[float], inertia: ArrayLike | None = None
) -> Array:
    """x = (m, m c_b / LENGTH, I_pb / INERTIA_LENGTH^2) for the inertia about the centre
    of mass `inertia` (3 x 3, platform frame; zeros if None)."""
    c = np.asarray(center_of_mass, dtype=float)
    I_c = np.zeros((3, 3)) if inertia is None else np.asarray(inertia, dtype=float)
    I_p = I_c + mass * (c.dot(c) * np.eye(3) - np.outer(c, c))
    entries = [I_p[i, j] / INERTIA_LENGTH**2 for i, j in _INERTIA_ENTRIES]
    return np.array([mass, *(mass * c / LENGTH), *entries])


def mass_and_com(x: ArrayLike) -> tuple[float, tuple[float, float, float]]:
    """(m, c_b) of x."""
    m, hx, hy, hz = (float(v) for v in np.asarray(x)[:4].tolist())
    return m, (LENGTH * hx / m, LENGTH * hy / m, LENGTH * hz / m)


def inertia_about_com(x: ArrayLike) -> Array:
    """I_b, the inertia about the centre of mass (3 x 3, platform frame), of x."""
    x = np.asarray(x, dtype=float)
    mass, com = mass_and_com(x)
    I_p = np.zeros((3, 3))
    for (i, j), value in zip(_INERTIA_ENTRIES, x[4:], strict=True):
        I_p[i, j] = I_p[j, i] = value * INERTIA_LENGTH**2
    c = np.array(com)
    return I_p - mass * (c.dot(c) * np.eye(3) - np.outer(c, c))


class PayloadEstimate:
    """The online estimate of `robot`'s platform mass, centre of mass and inertia (module
    docstring), for cycles `period` s apart and drives whose force follows their commands
    with a first-order lag `drive_lag` (s; the drums' m0 and k0 are the robot file's).
    `platform` is the model to use: the robot file's until the estimate moves it."""

    def __init__(
        self, robot: Robot, spec: AdaptationSpec, period: float, drive_lag: float
    ) -> None:
        self.file = robot.platform
        self.limits = payload_limits(robot, spec)
        self.frozen = spec.frozen
        self.inertia = spec.inertia  # estimate the inertia too (where rotation excites it)
        self._robot = robot
        self._m0, self._k0 = robot.m0, robot.k0
        self._elastic = bool(np.any(robot.compliance > 0.0))
        self._strain_lag = robot.strain_lag if np.any(robot.strain_lag > 0.0) else None
        self.period = period
        self._lag = drive_lag
        self._recent: deque[tuple] = deque()
        self.set_latency(0.0)
        self._take_latency()
        self._forget = math.exp(-SAMPLE_EVERY * period / WINDOW)
        self._gain = SOLVE_EVERY * period / (spec.time_constant + SOLVE_EVERY * period)
        self._dead_zone = DEAD_ZONE * self.file.mass
        self.platform = self.file
        # the estimate, unbounded (the fault check)
        self._x = parameters(self.file.mass, self.file.center_of_mass, self.file.inertia)
        self._observed: tuple | None = None  # the last cycle (observe)
        self.fault = ""
        self.clear()

    @property
    def mass(self) -> float:
        return self.platform.mass

    @property
    def center_of_mass(self) -> tuple[float, float, float]:
        return self.platform.center_of_mass

    def clear(self) -> None:
        """Forget the data and a fault; the estimate restarts from the model in use (at
        enable: a payload still beyond the limits faults again once it is seen)."""
        self._sums = np.zeros((PARAMETERS + 1, PARAMETERS + 1))
        self._weight = 0.0
        self._cycles = 0
        self._recent.clear()  # the last cycles, as many as a sample needs
        platform = self.platform
        self._x = parameters(platform.mass, platform.center_of_mass, platform.inertia)
        self.fault = ""

    def set(self, mass: float, center_of_mass: Sequence[float]) -> None:
        """Use this mass and centre of mass (identify-payload's, applied), within the limits
        (ValueError naming the limit if not); the online data restart from it."""
        problem = self._beyond(parameters(mass, center_of_mass, self.platform.inertia))
        if problem:
            raise ValueError(problem)
        self.platform = self._inertia(mass, center_of_mass, self.platform.inertia)
        self.clear()

    def observe(
        self, t: float, pose: Pose, fk: FKResult, lengths: Array, stretched_by: Array,
        compliance_scale: float, rates: Array, commands: Array, reference: Reference,
    ) -> None:  # fmt: skip
        """A cycle at time t: the platform measured at `pose` (forward kinematics `fk` from
        the drums' `lengths` stretched by the tensions `stretched_by`, with the robot
        file's compliance times `compliance_scale`: cdpr.stretch), the drums' `rates`,
        the `commands` the cycle sent and the `reference` at t: kept for `update` (the
        cycle's slack)."""
        if not self.frozen:  # copies: the caller's arrays may be reused
            self._observed = (
                t, pose, fk, lengths.copy(), stretched_by * compliance_scale, rates.copy(),
                commands, reference, compliance_scale,
            )  # fmt: skip

    def set_latency(self, latency: float) -> None:
        """The time (s) from a measurement to its command reaching the drives, taken in by
        the next update(): a daemon's cycle hands it over after its commands, and the
        weights it needs (tens of microseconds) are the slack's work, not the cycle's."""
        self._latency = latency

    def _take_latency(self) -> None:
        """The force weights and the window for the latency last set."""
        latency, self._latency = self._latency, None
        assert latency is not None
        self._weights, self._newest = drive_force_weights(self.period, self._lag, latency)
        # a sample: SPAN cycles either side of it, and its window's commands (one cycle
        # more either side for the force's rate)
        oldest = self._newest - len(self._weights)
        self._recent = deque(self._recent, maxlen=SPAN + 1 + max(SPAN, -oldest))

    def update(self) -> bool:
        """Once a cycle: take in the last observed cycle (the drives' force follows its
        commands), every SAMPLE_EVERY cycles the one SPAN cycles before it into the
        regression (its drums' acceleration needs the cycles around it), every
        SOLVE_EVERY cycles (on another cycle) move the estimate.  True when the model
        (`platform`) changed."""
        if self._latency is not None:
            self._take_latency()
        observed, self._observed = self._observed, None
        self._cycles += 1
        phase = self._cycles % SOLVE_EVERY
        recent = self._recent
        if observed is None or (
            recent and abs(observed[0] - recent[-1][0] - self.period) > GAP * self.period
        ):
            recent.clear()  # a cycle without a command, or a restart: start over
        if observed is not None:
            recent.append(observed)
        if phase == SAMPLE_EVERY // 2:
            return self._solve()
        if len(recent) == recent.maxlen and phase % SAMPLE_EVERY == 0:
            self._take_in(recent)
        return False

    def _take_in(self, recent: deque[tuple]) -> None:
        """The regression's row of the cycle SPAN cycles before the last of `recent`
        (module docstring)."""
        pose, tension, reference = self.sample(recent)
        platform = self._robot.jacobian(pose).T.dot(tension)
        row = regressor(pose, reference.accel.tolist(), reference.twist.tolist(),
                        self.file.gravity, platform.tolist())  # fmt: skip
        Z = np.array(row).reshape(6, PARAMETERS + 1)
        self._sums *= self._forget
        self._sums += Z.T.dot(Z)
        self._weight = self._weight * self._forget + 1.0

    def sample(self, recent: deque[tuple]) -> tuple[Pose, Array, Reference]:
        """The cycle SPAN cycles before the last of `recent` (full): the platform's pose,
        minus the cables' tensions and the reference at its measurement instant."""
        _, pose, fk, lengths, stretched_by, rates, _, reference, scale = recent[-1 - SPAN]
        # the drive's force over the period centred on the sample: the commands that act
        # in it (the newest first), weighted
        newest = -1 - SPAN + self._newest
        force = self._mean_force(recent, newest)
        # the drives' rates are means over the period before their measurement
        rate = 0.5 * (rates + recent[-SPAN][5])
        span = SPAN * self.period
        accel = (recent[-1][3] - 2.0 * lengths + recent[-1 - 2 * SPAN][3]) / (span * span)
        # minus the cables' tensions (the commands' sign): the force less the back-EMF
        # (through the drive's lag too: k0 (l' - lag l'')), the friction and the drum's
        # inertia
        tension = force - self._robot.drag(rate) - (self._m0 - self._k0 * self._lag) * accel
        if self._elastic and fk.normal_factor is not None:  # by these tensions' stretch
            stretched = tension
            if self._strain_lag is not None:  # which the strain follows D / EA late
                later, earlier = (self._mean_force(recent, newest + d) for d in (1, -1))
                tension_rate = 0.5 * (later - earlier) / self.period - self._k0 * accel
                stretched = tension - self._strain_lag * tension_rate
            stretch = lengths * self._robot.compliance  # stretched_by: scaled already
            change = stretch * (-stretched * scale - stretched_by)
            moved, _ = dpotrs(fk.normal_factor, change.dot(fk.jacobian))
            pose = retract(pose, moved)
        return pose, tension, reference

    def _mean_force(self, recent: deque[tuple], newest: int) -> Array:
        """The drives' force over the period centred on a cycle whose newest command acting
        in it is recent[newest] (drive_force_weights)."""
        return self._weights.dot([recent[newest - j][6] for j in range(len(self._weights))])

    def _solve(self) -> bool:
        if self._weight == 0.0:
            return False
        mean = self._sums / self._weight
        n = PARAMETERS if self.inertia else 4
        A, b = mean[:n, :n], mean[:n, PARAMETERS]
        x = self._x
        if n < PARAMETERS:  # the inertia as the model has it: its torque is known
            b = b - mean[:n, n:PARAMETERS].dot(x[n:])
            x = x[:n]
        values, vectors = np.linalg.eigh(A)
        excited = vectors[:, values > EXCITED]
        if excited.shape[1] == 0:
            return False
        # towards the least-squares solution in the excited directions, as far as it lies
        # beyond the dead zone
        along = excited.T.dot(b) / values[values > EXCITED] - excited.T.dot(x)
        distance = math.sqrt(float(along.dot(along)))
        if distance <= self._dead_zone:
            return False
        along *= 1.0 - self._dead_zone / distance
        x = x + self._gain * excited.dot(along)
        # and in the others the centre of mass and the inertia about it where they were
        # (a new mass at the old centre of mass, not at p)
        others = vectors[:, values <= EXCITED]
        inertia = inertia_about_com(self._x)
        if others.shape[1]:
            kept = parameters(float(x[0]), mass_and_com(self._x)[1], inertia)[:n]
            x = x + others.dot(others.T.dot(kept - x))
        # the same inertia about the new centre of mass where no rotation excites it
        if n < PARAMETERS or not np.any(np.abs(excited[4:]) > UNSEEN):
            mass, com = mass_and_com(x)
            x = parameters(mass, com, inertia)
        self._x = x
        problem = self._beyond(x)
        if problem:
            self.fault = problem
            return False
        mass, com = mass_and_com(x)
        self.platform = self._inertia(mass, com, inertia_about_com(x))
        return True

    def _beyond(self, x: Array) -> str:
        """Why x lies beyond the limits ("" if it does not)."""
        mass, com = mass_and_com(x)
        low, high, com_max, scale = self.limits
        if not low <= mass <= high:
            key, limit = ("mass_max", high) if mass > high else ("mass_min", low)
            return (
                f"payload beyond limits: platform mass {mass:.3g} kg, "
                f"adaptation.{key} {limit:g} kg"
            )
        moved = math.dist(com, self.file.center_of_mass)
        if moved > com_max:
            return (
                f"payload beyond limits: centre of mass {moved * 1e3:.0f} mm from the robot "
                f"file's, adaptation.com_max {com_max * 1e3:.0f} mm"
            )
        inertia = inertia_about_com(x)
        ratios = np.diag(inertia) / np.diag(self.file.inertia)
        if not np.all(np.linalg.eigvalsh(inertia) > 0.0) or not (
            1.0 / scale <= ratios.min() and ratios.max() <= scale
        ):
            return (
                f"payload beyond limits: inertia diagonal {np.diag(inertia).round(4).tolist()} "
                f"kg m^2, adaptation.inertia_scale_max {scale:g} of the robot file's "
                f"{np.diag(self.file.inertia).round(4).tolist()}"
            )
        return ""

    def _inertia(self, mass: float, com: Sequence[float], inertia: Array) -> PlatformInertia:
        return PlatformInertia(mass, com, inertia, self.file.gravity)


def drive_force_weights(period: float, lag: float, latency: float) -> tuple[Array, int]:
    """(w, newest): the drive's force averaged over the period centred on a measurement
    instant t_k is w . (c_newest, c_newest-1, ...), c_j the command of cycle k + j, for
    commands that reach the drive `latency` s after their measurement and are held there,
    the force following them through a first-order lag (s).  The force ripples within
    each cycle as its command lands, and where in the cycle t_k falls depends on the
    latency; over a whole period the ripple averages out, while the smooth part's mean is
    its value at t_k to T^2 / 24 of its curvature.  Commands whose share is below
    FORGOTTEN are left out, and w sums to 1.  The shares in closed form (integrals of
    exponentials): the controller recomputes them whenever its latency median moves,
    inside a cycle (a quadrature took 0.3 ms at 1 kHz)."""
    half = 0.5 * period

    def rise(lo: float, hi: float, start: float) -> float:  # integral of 1 - e^-(u-start)/lag
        if lag <= 0.0:
            return hi - lo
        return hi - lo - lag * (math.exp((start - lo) / lag) - math.exp((start - hi) / lag))

    def share(j: int) -> float:  # of command j, held over [a, b), in the period's mean
        a, b = j * period + latency, (j + 1) * period + latency
        total = 0.0
        lo, hi = max(a, -half), min(b, half)
        if hi > lo:  # while it is held: the force rises towards it
            total += rise(lo, hi, a)
        lo = max(b, -half)
        if half > lo and lag > 0.0:  # after it: what is left of its rise
            total += rise(lo, half, a) - rise(lo, half, b)
        return total / period

    newest = math.ceil((half - latency) / period) - 1  # the last to land in the period
    w = []
    j = newest
    while True:
        w.append(share(j))
        if j * period + latency < -half and w[-1] < FORGOTTEN:
            break
        j -= 1
    weights = np.array(w[:-1])
    return weights / weights.sum(), newest


class StaticFit(NamedTuple):
    """identify-payload's estimate: mass (kg) and centre of mass (m, platform frame) with
    their standard deviations (inf for a component the poses did not reveal: it is the
    robot file's), the RMS of what the fit leaves of the wrenches (N, torques / LENGTH)
    and how many samples it used."""

    mass: float
    center_of_mass: tuple[float, float, float]
    mass_std: float
    center_of_mass_std: tuple[float, float, float]
    residual_rms: float
    samples: int


def static_fit(robot: Robot, samples: Sequence[tuple[Pose, ArrayLike]]) -> StaticFit:
    """The mass and centre of mass that explain the drives' `forces` holding the
    platform at rest at each `pose` (samples of (pose, forces)): the cables' wrench
    Lambda(pose)^T f balances m g and the moment (R m c_b) x g.  One pose reveals the mass
    and the centre of mass across gravity; poses tilted about two axes reveal all of it.
    ValueError if there are no samples."""
    if not samples:
        raise ValueError("static_fit: no samples")
    zero = [0.0] * 6
    rows = []
    for pose, forces in samples:
        wrench = robot.jacobian(pose).T.dot(np.asarray(forces, dtype=float))
        row = regressor(pose, zero, zero, robot.platform.gravity, wrench.tolist())
        # at rest the inertia's columns are zero: mass and first moment only
        rows.append(np.array(row).reshape(6, PARAMETERS + 1)[:, [0, 1, 2, 3, PARAMETERS]])
    Z = np.concatenate(rows)
    Y, y = Z[:, :4], Z[:, -1]
    values, vectors = np.linalg.eigh(Y.T.dot(Y) / len(samples))
    excited = values > EXCITED
    V, lam = vectors[:, excited], values[excited]
    file = robot.platform
    x = V.dot(V.T.dot(Y.T.dot(y)) / len(samples) / lam)
    if not excited.all():  # the centre of mass along what was not seen: the file's
        U = vectors[:, ~excited]
        kept = parameters(float(x[0]), file.center_of_mass)[:4]
        x = x + U.dot(U.T.dot(kept - x))
    residual = y - Y.dot(x)
    dof = max(len(y) - int(excited.sum()), 1)
    sigma2 = float(residual.dot(residual)) / dof
    # covariance of x in the revealed directions; unrevealed ones: unbounded
    cov = V.dot(V.T / lam[:, None]) * sigma2 / len(samples)
    mass, com = mass_and_com(x)
    # c = LENGTH h' / m: its first-order sensitivity to (m, h')
    J = np.zeros((3, 4))
    J[:, 0] = -np.asarray(com) / mass
    J[:, 1:] = np.eye(3) * LENGTH / mass
    com_var = np.diag(J.dot(cov).dot(J.T))
    if not excited.all():
        hidden = np.abs(vectors[1:, ~excited]).max(axis=1) > 0.1  # per platform axis
        com_var = np.where(hidden, math.inf, com_var)
    std = tuple(math.sqrt(max(float(v), 0.0)) for v in com_var)
    return StaticFit(
        mass, com, math.sqrt(max(float(cov[0, 0]), 0.0)), std,  # type: ignore[arg-type]
        math.sqrt(float(residual.dot(residual)) / len(y)), len(samples),
    )  # fmt: skip
