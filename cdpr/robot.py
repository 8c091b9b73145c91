"""The Robot: one validated description and the model computations on it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.body import PlatformBody
from cdpr.compiled_model import model_rows
from cdpr.description import (
    ActuatorSpec,
    ConfigError,
    RobotSpec,
    load_yaml,
    parse_robot,
    show_path,
)
from cdpr.dynamics import PlatformInertia, modal_masses
from cdpr.forward_kinematics import (
    FKResult,
    FKSettings,
    Linearisation,
    linearise,
    solve_forward_kinematics,
)
from cdpr.friction import friction_direction
from cdpr.kinematics import CableGeometry
from cdpr.pose import Pose
from cdpr.so3 import quat_to_r9

Array = NDArray[np.float64]


class Robot:
    """A cable-driven parallel robot: geometry, platform inertia and actuators.

    Build it with ``Robot.from_yaml(path)`` or ``Robot.from_dict(d)``.  Twists and
    accelerations are length-6 arrays (v, omega) in mixed coordinates (DESIGN §3).
    """

    def __init__(self, spec: RobotSpec) -> None:
        self.spec = spec
        self.name = spec.name
        self.actuators: list[ActuatorSpec] = [spec.actuator_of(i) for i in range(len(spec.cables))]
        self.geometry = CableGeometry(
            np.array([c.anchor for c in spec.cables]),
            np.array([c.attachment for c in spec.cables]),
            [None if c.pulley is None else (c.pulley.radius, c.pulley.axis) for c in spec.cables],
        )
        body = spec.platform.body
        # the corners the pose limits keep in the workspace and clear of the environment
        self.body = PlatformBody(body.corners() if body else (), self.geometry.attachments)
        self.platform = PlatformInertia(
            spec.platform.mass,
            spec.platform.center_of_mass,
            np.array(spec.platform.inertia),
            spec.gravity,
        )
        self.m0 = np.array([a.m0 for a in self.actuators])
        self._m0 = np.array(self.m0, dtype=float)  # the kernels' own copy
        self.k0 = np.array([a.k0 for a in self.actuators])
        self.t_min = np.array([a.t_min for a in self.actuators])
        self.force_max = np.array([a.force_max for a in self.actuators])
        self.length_min = np.array([a.length_min for a in self.actuators])
        self.length_max = np.array([a.length_max for a in self.actuators])
        self.cable_diameter = np.array([a.diameter for a in self.actuators])
        self.compliance = np.array(
            [0.0 if a.cable_stiffness is None else 1.0 / a.cable_stiffness for a in self.actuators]
        )
        # s: how far each cable's strain lags its tension (damping / EA)
        self.strain_lag = self.compliance * [a.cable_damping or 0.0 for a in self.actuators]
        self.friction = np.array([a.friction or 0.0 for a in self.actuators])  # N, Coulomb
        self._frictional = bool(np.any(self.friction > 0.0))
        self.home = Pose(spec.home.position, spec.home.quaternion.as_tuple())
        self.poses = {"home": self.home} | {
            name: Pose(p.position, p.quaternion.as_tuple()) for name, p in spec.poses.items()
        }
        fk = spec.forward_kinematics
        self.fk_settings = FKSettings(fk.max_iterations, fk.step_tolerance, fk.max_residual)
        self._check_home()
        self._load_kernels()

    def _load_kernels(self) -> None:
        """Call every compiled kernel a control cycle runs, once, where a robot is built:
        numba loads each from its cache (or, cold, compiles it) at its first call, which
        must not be a cycle's (0.25 s from the cache on this host; seconds to compile)."""
        home = self.home
        lengths = self.cable_lengths(home)
        self.forward_kinematics(lengths, self.linearise_at(home))
        self.forward_kinematics(lengths, home)
        self.model_terms(home, _ZERO_TWIST)
        self.bias_accel(home, _ZERO_TWIST)

    @classmethod
    def from_dict(cls, data: Any, source: str = "robot", key: str = "") -> Robot:
        """Validate and build; ConfigError names each bad key (`source`: the file or what
        the data came from, `key`: where the description sits in it)."""
        spec = parse_robot(data, source, key)
        try:
            return cls(spec)
        except ConfigError as exc:
            raise exc.within(": ".join(p for p in (source, key) if p)) from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> Robot:
        """Load a robot description file (see config/robots/)."""
        return cls.from_dict(load_yaml(path), source=show_path(path))

    @classmethod
    def from_reference(
        cls, value: Any, base: Path, source: str = "config", key: str = "robot"
    ) -> Robot:
        """The `robot:` entry (`key`) of a daemon config (`source`): a file path (relative
        to `base`, the config file's directory) or an inline description."""
        if isinstance(value, str):
            path = Path(value)
            path = path if path.is_absolute() else base / path
            try:
                data = load_yaml(path)
            except ConfigError as exc:  # unreadable, or not YAML: name the key too
                raise exc.within(f"{source}: {key}") from None
            return cls.from_dict(data, source=show_path(path))
        if isinstance(value, dict):
            return cls.from_dict(value, source, key)
        raise ConfigError(
            f"{source}: {key}: expected a mapping or a path to a robot file, "
            f"got {type(value).__name__}"
        )

    @property
    def n_cables(self) -> int:
        return self.geometry.n

    def slack(self, tensions: ArrayLike) -> Array:
        """Which cables are slack: tension <= 0, or below the cable's t_min (booleans)."""
        t = np.asarray(tensions, dtype=float)
        return (t <= 0.0) | (t < self.t_min)

    # -- kinematics -----------------------------------------------------------------

    def cable_lengths(self, pose: Pose) -> Array:
        """L(eta): cable lengths (m)."""
        return self.geometry.table(pose.position_tuple, pose.quaternion_tuple)[1]

    def jacobian(self, pose: Pose) -> Array:
        """Lambda(eta), n x 6, with l_dot = Lambda phi."""
        return self.lengths_and_jacobian(pose)[1]

    def lengths_and_jacobian(self, pose: Pose) -> tuple[Array, Array]:
        """L(eta) and Lambda(eta) (contiguous) in one pass."""
        table, lengths = self.geometry.table(pose.position_tuple, pose.quaternion_tuple)
        return lengths, np.ascontiguousarray(table[:, :6])

    def bias_accel(self, pose: Pose, twist: ArrayLike) -> Array:
        """c(eta, phi) with l_ddot = Lambda alpha + c."""
        phi = _twist_tuple(twist)
        return self.geometry.table(pose.position_tuple, pose.quaternion_tuple, phi)[0][:, 6].copy()

    def drag(self, rates: Array) -> Array:
        """The force (N, commands' sign) the winches add to move their drums at `rates`
        (m/s): the back-EMF k0 l' and the Coulomb friction against the motion
        (cdpr.friction)."""
        if self._frictional:
            return self.k0 * rates + self.friction * friction_direction(rates)
        return self.k0 * rates

    def stretched_lengths(self, drum_lengths: ArrayLike, tensions: ArrayLike) -> Array:
        """Geometric cable lengths from the lengths the drums paid out, under `tensions`
        (elastic cables, DESIGN §12): L = l (1 + t / EA).  Identity for inextensible ones."""
        drum = np.asarray(drum_lengths, dtype=float)
        return drum + drum * self.compliance * np.asarray(tensions, dtype=float)

    def drum_lengths(self, lengths: ArrayLike, tensions: ArrayLike) -> Array:
        """The inverse of stretched_lengths: what the drums pay out for geometric
        `lengths` under `tensions`."""
        return np.asarray(lengths, dtype=float) / (1.0 + self.compliance * np.asarray(tensions))

    def forward_kinematics(
        self, lengths: ArrayLike, guess: Pose | Linearisation | None = None
    ) -> FKResult:
        """Y(l): warm-start from `guess` (e.g. the last pose, or linearise_at()'s
        linearisation at it), else cold-start from home.

        Never raises on a bad measurement; see FKResult.converged and .reason.
        """
        return solve_forward_kinematics(
            self.geometry, lengths, self.home if guess is None else guess, self.fk_settings
        )

    def linearise_at(self, guess: Pose) -> Linearisation:
        """What forward_kinematics(lengths, guess) computes of the guess alone, ahead of
        the lengths (cdpr.forward_kinematics.Linearisation): pass it as the guess."""
        return linearise(self.geometry, guess)

    # -- dynamics -------------------------------------------------------------------

    def dynamics(self, pose: Pose, twist: ArrayLike) -> tuple[Array, Array]:
        """(M, mu) at (eta, phi): tau = M alpha + mu, actuator inertia m0 included."""
        G = self.model_tables(pose, twist)[1]
        return G[:6, :6], G[:6, 6]

    def model_terms(self, pose: Pose, twist: ArrayLike) -> tuple[Array, Array, Array, Array]:
        """(Lambda, c, M, mu) at (eta, phi) from one kinematics pass: what a control
        cycle needs of the model.  Lambda is contiguous: a control cycle multiplies with
        it several times (see the cdpr.kinematics docstring)."""
        return split_model(*self.model_tables(pose, twist))

    def model_tables(self, pose: Pose, twist: ArrayLike) -> tuple[Array, Array]:
        """The n x 7 table [Lambda | c] and a 7 x 7 matrix whose first 6 rows are [M | mu]:
        [Lambda | c]^T diag(m0) [Lambda | c] holds Lambda^T D Lambda and Lambda^T D c, to
        which [M_p | mu_p] is added (one compiled kernel, cdpr.compiled_model)."""
        n = self.geometry.n
        table, G = np.empty((n, 7)), np.empty((7, 7))
        model_rows(
            self.geometry.rows, self.platform.rows, self._m0,
            pose.position_tuple, pose.quaternion_tuple, _twist_tuple(twist), table, G,
        )  # fmt: skip
        return table, G

    def mass_matrix(self, pose: Pose) -> Array:
        """M(eta) = M_p + Lambda^T diag(m0) Lambda (6 x 6, symmetric positive definite)."""
        return self.dynamics(pose, _ZERO_TWIST)[0]

    def bias_wrench(self, pose: Pose, twist: ArrayLike) -> Array:
        """mu(eta, phi): velocity-dependent and gravity-compensating part of tau."""
        return self.dynamics(pose, twist)[1]

    def modal_masses(self, pose: Pose) -> Array:
        """Lemma 1: m_i = 1 / eig(M^-1 Lambda^T Lambda), ascending, each in [m0, inf]."""
        return modal_masses(self.mass_matrix(pose), self.jacobian(pose))

    # -- checks ---------------------------------------------------------------------

    def length_violations(self, lengths: ArrayLike) -> list[str]:
        """Human-readable list of cables outside [length_min, length_max]."""
        lengths = np.asarray(lengths, dtype=float)
        out = []
        for k, (ell, lo, hi) in enumerate(
            zip(lengths, self.length_min, self.length_max, strict=True)
        ):
            if not lo <= ell <= hi:
                out.append(f"cable {k} length {ell:.4f} m outside [{lo:.4f}, {hi:.4f}] m")
        return out

    def _check_home(self) -> None:
        """At the home pose every cable has a finite length and a direction (a zero-length
        cable has none), within its limits, and Lambda has full rank."""
        home, geometry = self.home, self.geometry
        R = np.array(quat_to_r9(*home.quaternion_tuple)).reshape(3, 3)
        with np.errstate(all="ignore"):
            spans = home.position + geometry.attachments @ R.T - geometry.anchors
            spans = np.linalg.norm(spans, axis=1)
        if not np.all(np.isfinite(spans)):
            raise ConfigError("cables: the cable geometry at the home pose is not finite")
        for k, (span, pulley) in enumerate(zip(spans.tolist(), geometry.pulleys, strict=True)):
            if pulley is None and not span > 1e-9:
                raise ConfigError(
                    f"cables.{k}: the cable has zero length at the home pose (its attachment "
                    "meets its anchor)"
                )
        try:
            lengths, Lam = self.lengths_and_jacobian(home)
        except ZeroDivisionError:  # an attachment at the centre of its pulley
            raise ConfigError("cables: a pulley cable has no direction at the home pose") from None
        problems = self.length_violations(lengths)
        if problems:
            raise ConfigError("home: the home pose puts " + "; ".join(problems))
        sv = np.linalg.svd(Lam, compute_uv=False)
        if not sv[-1] >= 1e-6 * sv[0]:
            raise ConfigError(
                "home: Jacobian Lambda is rank deficient at the home pose "
                f"(singular values {np.array2string(sv, precision=3)})"
            )


_ZERO_TWIST = (0.0,) * 6


def split_model(table: Array, G: Array) -> tuple[Array, Array, Array, Array]:
    """(Lambda (a contiguous copy), c, M, mu) of Robot.model_tables' (table, G); c, M and
    mu are views of them."""
    return np.ascontiguousarray(table[:, :6]), table[:, 6], G[:6, :6], G[:6, 6]


def _twist_tuple(twist: ArrayLike) -> tuple[float, ...]:
    """A twist as the kernels take it: a tuple of 6 floats."""
    phi = tuple(twist.tolist() if isinstance(twist, np.ndarray) else [float(c) for c in twist])
    if len(phi) != 6 or not isinstance(phi[0], float):
        raise ValueError(f"a twist is 6 numbers (v, omega), got {twist!r}")
    return phi
