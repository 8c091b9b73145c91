"""Geometric self-calibration from redundant cable lengths (DESIGN §15
step 5).

Data: the platform at rest at m poses (unknown: the model is what is being found), at
each the lengths the drives read (with the offsets that were in force) and the forces
they were commanded (at rest, minus the tensions).  With n > 6 cables each pose gives
n - 6 equations beyond its own six unknowns.

Model, per cable k and pose j (DESIGN §3; cdpr.stretch's stretch):
    raw_kj = read length - offset in force        (motor position x metres per count)
    drum_kj = o_k + s_k (raw_kj - mean_j raw_kj)  (o_k: drum length at the mean reading;
                                                   the true drum radius is s_k x the file's)
    t_kj = -f_kj                                  (a radius error's effect on the force,
                                                   (s_k - 1) t, is neglected)
    |p_j + R_j b_k - a_k| = drum_kj (1 + c t_kj / EA_k)
Unknowns: anchors a_k, attachments b_k, offsets o_k, drum radius scales s_k, one
compliance scale c of the file's 1/EA (the found EA is the file's over c), and the poses.
Gravity's direction in the calibrated frame follows: at rest the cables carry the
platform, sum_k t_k u_k = m g (its magnitude stays the file's); without it a frame
tilted by a few mrad would make the controller's gravity model push sideways.

Gauge freedoms, fixed explicitly: moving every anchor and every pose by one rigid motion
changes no length, nor does moving the platform frame (every attachment, and every pose
the other way), nor scaling the whole robot with every drum radius (a robot 1 % larger
with 1 % larger drums reads the same).  The anchor corrections are kept orthogonal to
the six infinitesimal rigid motions of the file's anchors: the world frame is the file's
anchor frame in the least-squares sense (the corrected anchors' best rigid fit onto the
file's is the identity).  The attachment corrections are kept orthogonal to the rigid
motions of the file's attachments (the platform frame).  The fit takes the scale from
the drums: their radius scales keep a mean of 1 (the scales find the drums' differences).
Lengths alone cannot see a common drum radius error: a fit of drums 1 % larger than the
file's is the true robot 1 % too small (`scale_cost`).  A measured distance between two
anchors (`AnchorDistance`) sets the scale after the fit (`scaled`).

Identifiability: the poses are eliminated (the parameter Jacobian projected onto the
orthogonal complement of the pose columns), the columns scaled to unit norm, and the
singular values of what remains show which combinations the data determine.  A
combination whose singular value is below RANK_TOLERANCE of the largest is not
identifiable: it is held at the file's value (the solve runs in the span of the others)
and the report names the parameters it involves.  `predicted_std` is each parameter's
standard deviation for a length noise `noise` (m) from that Jacobian.

scipy.optimize.least_squares solves; `select_poses` picks poses greedily for the largest
determinant of the information matrix (D-optimal) from candidates inside the workspace.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from cdpr import Pose, Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import static_tensions, tension_solver
from cdpr.so3 import exp_so3

Array = NDArray[np.float64]
RANK_TOLERANCE = 1e-6  # singular value (unit-norm columns) / the largest: not identifiable
MAX_NFEV = 300  # residual evaluations per solve
NOISE = 1e-5  # m: length noise assumed for the predicted standard deviations
TENSION_MARGIN = 2.0  # candidate poses: the lowest planned tension at least this x t_min
FORCE_SHARE = 0.8  # and the highest at most this share of force_max
GROUPS = ("anchors", "attachments", "offsets", "drum_radius_scale", "stiffness")
Progress = Callable[[str], None]


@dataclass(frozen=True)
class Sample:
    """The platform at rest: the lengths the drives read (m, with `offsets` in force) and
    the forces they were commanded (N along +l; minus the tensions)."""

    lengths: Array
    forces: Array


@dataclass
class Calibration:
    """What the fit found (world frame: the file's anchor frame, module docstring)."""

    anchors: Array  # n x 3, world frame
    attachments: Array  # n x 3, platform frame
    offsets: Array  # n, m: the cable length at motor position 0 (the drives' length_offset)
    drum_radius_scale: Array  # n: true drum radius / the file's
    stiffness_scale: float  # the cables' EA / the file's
    gravity: Array  # m/s^2 in the calibrated world frame (its direction from the tensions)
    poses: list[Pose]
    residual_rms: float  # m
    residual_max: float  # m
    singular_values: Array  # of the scaled, pose-eliminated identification Jacobian
    condition: float  # largest / smallest identifiable singular value
    unidentifiable: list[str]  # one line per combination held at the file's value
    predicted_std: dict[str, float]  # per group: the largest predicted std (its unit)
    iterations: int = 0
    converged: bool = True  # the solver met its tolerances within MAX_NFEV

    def report(self) -> dict[str, Any]:
        """The figures (for JSON and the command line)."""
        return {
            "residual_rms_mm": self.residual_rms * 1e3,
            "residual_max_mm": self.residual_max * 1e3,
            "condition": self.condition,
            "singular_values": {
                "largest": float(self.singular_values.max()),
                "smallest": float(self.singular_values.min()),
                "count": len(self.singular_values),
            },
            "unidentifiable": self.unidentifiable,
            "predicted_std": self.predicted_std,
            "stiffness_scale": self.stiffness_scale,
            "drum_radius_scale": self.drum_radius_scale.tolist(),
            "offsets": self.offsets.tolist(),
            "poses": len(self.poses),
            "iterations": self.iterations,
            "converged": self.converged,
        }


def rigid_complement(points: Array) -> Array:
    """An orthonormal basis (3n x (3n - 6)) of the corrections of `points` (n x 3) with no
    component along an infinitesimal rigid motion of them: the gauge fix."""
    centred = points - points.mean(axis=0)
    motions = []
    for axis in np.eye(3):
        motions.append(np.tile(axis, len(points)))  # translation
        motions.append(np.cross(axis, centred).reshape(-1))  # rotation about the centroid
    u, _, _ = np.linalg.svd(np.array(motions).T, full_matrices=True)
    return u[:, len(motions) :]


def rigid_complement_scales(n: int) -> Array:
    """An orthonormal basis (n x (n - 1)) of the radius scale changes with zero mean."""
    u, _, _ = np.linalg.svd(np.ones((n, 1)), full_matrices=True)
    return u[:, 1:]


class _Model:
    """The parameter vector: [anchor gauge coords | attachment gauge coords | o (n) |
    s (n) | c], then 6 per pose (position, rotation vector about the initial pose)."""

    def __init__(self, robot: Robot, offsets: Array, samples: Sequence[Sample]) -> None:
        self.robot = robot
        self.n = n = robot.n_cables
        self.m = len(samples)
        self.anchors0 = np.array(robot.geometry.anchors, dtype=float)
        self.attachments0 = np.array(robot.geometry.attachments, dtype=float)
        self.Pa = rigid_complement(self.anchors0)
        self.Pb = rigid_complement(self.attachments0)
        self.Ps = rigid_complement_scales(n)
        # the physical parameters each group's coordinates move (None: one to one)
        self.bases = {"anchors": self.Pa, "attachments": self.Pb, "drum_radius_scale": self.Ps}
        self.na = self.Pa.shape[1]
        self.nb = self.Pb.shape[1]
        self.raw = np.array([s.lengths for s in samples]) - offsets  # m x n
        self.forces = np.array([s.forces for s in samples])
        self.mean_raw = self.raw.mean(axis=0)
        self.compliance = np.array(robot.compliance, dtype=float)
        self.n_params = self.na + self.nb + 2 * n
        # slices of the parameter vector
        i = 0
        self.slices: dict[str, slice] = {}
        for name, size in zip(GROUPS, (self.na, self.nb, n, n - 1, 1), strict=True):
            self.slices[name] = slice(i, i + size)
            i += size

    def initial(self, offsets: Array, poses: Sequence[Pose]) -> Array:
        """The file's parameters (offsets in force, radius scale 1, stiffness scale 1)."""
        theta = np.zeros(self.n_params)
        theta[self.slices["offsets"]] = offsets + self.mean_raw  # drum length at mean raw
        theta[self.slices["stiffness"]] = 1.0
        self.base_poses = list(poses)
        return np.concatenate([theta, np.zeros(6 * self.m)])

    def unpack(self, x: Array) -> tuple[Array, Array, Array, Array, float, list[Pose]]:
        sl = self.slices
        anchors = self.anchors0 + (self.Pa @ x[sl["anchors"]]).reshape(self.n, 3)
        attachments = self.attachments0 + (self.Pb @ x[sl["attachments"]]).reshape(self.n, 3)
        o, c = x[sl["offsets"]], float(x[sl["stiffness"]][0])
        s = 1.0 + self.Ps @ x[sl["drum_radius_scale"]]
        poses = []
        deltas = x[self.n_params :].reshape(self.m, 6)
        for base, d in zip(self.base_poses, deltas, strict=True):
            R = exp_so3(d[3:]) @ base.rotation
            poses.append(Pose.from_matrix(base.position + d[:3], R))
        return anchors, attachments, o, s, c, poses

    def _terms(self, x: Array) -> tuple[Array, ...]:
        """Everything the residuals and their Jacobian share, for all poses at once."""
        anchors, attachments, o, s, c, _ = self.unpack(x)
        deltas = x[self.n_params :].reshape(self.m, 6)
        R = np.array(
            [exp_so3(d[3:]) @ b.rotation for b, d in zip(self.base_poses, deltas, strict=True)]
        )
        p = np.array([b.position for b in self.base_poses]) + deltas[:, :3]
        v = np.einsum("jab,kb->jka", R, attachments)  # R_j b_k, m x n x 3
        d = p[:, None, :] + v - anchors[None, :, :]
        length = np.linalg.norm(d, axis=2)
        tensions = -self.forces
        stretch = 1.0 + c * self.compliance * tensions
        drum = o + s * (self.raw - self.mean_raw)
        return d / length[:, :, None], v, R, length, stretch, drum, tensions, deltas, c

    def residuals(self, x: Array) -> Array:
        _, _, _, length, stretch, drum, *_ = self._terms(x)
        return (length - drum * stretch).reshape(-1)

    def jacobian(self, x: Array) -> Array:
        """Analytic: d|d|/da = -u, d|d|/db = u^T R, d|d|/dp = u, d|d|/dw = (R b x u)^T
        J_l(w) for R = exp(w) R_0; the drum and stretch terms are linear."""
        u, v, R, _, stretch, drum, tensions, deltas, _ = self._terms(x)
        m, n, P = self.m, self.n, self.n_params
        J = np.zeros((m, n, P + 6 * m))
        sl = self.slices
        rows = np.arange(n)
        Ja = np.zeros((m, n, n, 3))
        Ja[:, rows, rows, :] = -u
        J[:, :, sl["anchors"]] = Ja.reshape(m, n, 3 * n) @ self.Pa
        Jb = np.zeros((m, n, n, 3))
        Jb[:, rows, rows, :] = np.einsum("jka,jab->jkb", u, R)
        J[:, :, sl["attachments"]] = Jb.reshape(m, n, 3 * n) @ self.Pb
        J[:, rows, sl["offsets"].start + rows] = -stretch
        Js = np.zeros((m, n, n))
        Js[:, rows, rows] = -(self.raw - self.mean_raw) * stretch
        J[:, :, sl["drum_radius_scale"]] = Js @ self.Ps
        J[:, :, sl["stiffness"].start] = -drum * self.compliance * tensions
        cross = np.cross(v, u)  # m x n x 3
        for j in range(m):
            J[j, :, P + 6 * j : P + 6 * j + 3] = u[j]
            J[j, :, P + 6 * j + 3 : P + 6 * j + 6] = cross[j] @ _left_jacobian(deltas[j, 3:])
        return J.reshape(m * n, -1)


def _left_jacobian(w: Array) -> Array:
    """J_l(w) of SO(3): d exp(w) / dw = J_l(w) as a left perturbation."""
    theta = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * W
    return (
        np.eye(3)
        + (1.0 - math.cos(theta)) / theta**2 * W
        + (theta - math.sin(theta)) / theta**3 * (W @ W)
    )


def _eliminate_poses(J: Array, n_params: int) -> Array:
    """The parameter columns projected onto the orthogonal complement of the pose
    columns (what the data say about the parameters, whatever the poses)."""
    Jt, Jp = J[:, :n_params], J[:, n_params:]
    q, r = np.linalg.qr(Jp)
    keep = np.abs(np.diag(r)) > 1e-12 * max(1.0, float(np.abs(np.diag(r)).max()))
    q = q[:, keep]
    return Jt - q @ (q.T @ Jt)


def _group_of(model: _Model, index: int) -> str:
    for name, sl in model.slices.items():
        if sl.start <= index < sl.stop:
            return name
    raise IndexError(index)


def _identifiability(
    model: _Model, J: Array, noise: float
) -> tuple[Array, Array, Array, list[str], dict[str, float], Array]:
    """Of the pose-eliminated Jacobian with unit-norm columns: (its singular values, one
    per parameter coordinate, zeros where there are fewer equations; the right singular
    vectors of the identifiable span; the column scales; each unidentifiable combination
    as text; each group's largest predicted standard deviation for length noise `noise`,
    in the group's unit; the mask of identifiable singular values)."""
    reduced = _eliminate_poses(J, model.n_params)
    scales = np.linalg.norm(reduced, axis=0)
    scales[scales == 0.0] = 1.0
    _, sv, vt = np.linalg.svd(reduced / scales, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(len(vt) - len(sv))])  # fewer equations than unknowns
    good = sv > RANK_TOLERANCE * sv.max()
    lines = []
    for k in np.flatnonzero(~good):
        direction = vt[k] / scales
        direction /= np.abs(direction).max()
        parts = [
            _describe(model, int(i))
            for i in np.argsort(-np.abs(direction))[:6]
            if abs(direction[i]) >= 0.2
        ]
        lines.append(f"singular value {sv[k]:.2e}: " + " with ".join(dict.fromkeys(parts)))
    # covariance in the identifiable span, (V S^-2 V^T) noise^2, in parameter units
    V = vt[good].T / scales[:, None]
    cov = (V / sv[good] ** 2) @ V.T * noise**2
    predicted = {}
    for name, sl in model.slices.items():
        basis = model.bases.get(name)
        block = cov[sl, sl] if basis is None else basis @ cov[sl, sl] @ basis.T
        predicted[name] = float(np.sqrt(np.clip(np.diag(block), 0.0, None)).max())
    return sv, vt[good], scales, lines, predicted, good


def _describe(model: _Model, index: int) -> str:
    """The parameters coordinate `index` moves, in words."""
    group = _group_of(model, index)
    column = index - model.slices[group].start
    basis = model.bases.get(group)
    if group == "stiffness":
        return "the cables' EA"
    if basis is None:
        return f"{group}[{column}]"
    effect = np.abs(basis[:, column]).reshape(model.n, -1).sum(axis=1)
    cables = ", ".join(map(str, np.argsort(-effect)[:2]))
    words = {"anchors": "anchors", "attachments": "attachments", "drum_radius_scale": "drum radii"}
    return f"{words[group]} of cables {cables}"


def _initial_poses(robot: Robot, samples: Sequence[Sample]) -> list[Pose]:
    """Forward kinematics of each sample with the file's model (stretch under the
    measured tensions), warm-started from the previous one."""
    poses, guess = [], robot.home
    for sample in samples:
        stretched = robot.stretched_lengths(sample.lengths, -np.asarray(sample.forces))
        fk = robot.forward_kinematics(stretched, guess)
        if not np.all(np.isfinite(fk.pose.position)):
            raise ValueError("forward kinematics failed on a sample: lengths fit no pose")
        poses.append(fk.pose)
        guess = fk.pose
    return poses


def _offsets_fitted(
    robot: Robot, offsets: ArrayLike, samples: Sequence[Sample], say: Progress
) -> tuple[_Model, Array]:
    """The model of `samples` and its start: the file's parameters with the offsets
    alone fitted (when the lengths outnumber the offsets and poses).  Homing with wrong
    anchors, or none, leaves the offsets centimetres off, and the poses forward
    kinematics gave with them too."""
    offsets = np.asarray(offsets, dtype=float)
    if len(samples) < 2:
        raise ValueError(f"calibration needs poses: {len(samples)} given")
    model = _Model(robot, offsets, samples)
    x0 = model.initial(offsets, _initial_poses(robot, samples))
    say(f"identifiability: {len(samples)} poses, {model.n_params} parameters")
    if model.m * model.n >= model.n + 6 * model.m:  # else too few lengths to fit them
        only_offsets = np.eye(model.n_params)[:, model.slices["offsets"]]
        x0, _, _ = _least_squares(model, x0, only_offsets, say, "offsets")
    return model, x0


@dataclass(frozen=True)
class Identifiability:
    """What a set of poses can identify, before any fit of the geometry: the rank of the
    pose-eliminated identification Jacobian (columns scaled) among its parameter
    combinations, its condition over the identifiable ones, and each combination it
    cannot identify, in words."""

    poses: int
    parameters: int
    rank: int
    condition: float
    unidentifiable: list[str]


def survey(
    robot: Robot, offsets: ArrayLike, samples: Sequence[Sample], noise: float = NOISE
) -> Identifiability:
    """What `samples` (read with `offsets`) identify, at the file's geometry with the
    offsets fitted: for poses too few to calibrate with (a round interrupted), said
    instead of fitting.  ValueError as `identify`."""
    model, x0 = _offsets_fitted(robot, offsets, samples, lambda _text: None)
    sv, _, _, lines, _, good = _identifiability(model, model.jacobian(x0), noise)
    return Identifiability(
        poses=len(samples),
        parameters=len(sv),
        rank=int(good.sum()),
        condition=float(sv[good].max() / sv[good].min()),
        unidentifiable=lines,
    )


def identify(
    robot: Robot,
    offsets: ArrayLike,
    samples: Sequence[Sample],
    noise: float = NOISE,
    progress: Progress | None = None,
) -> Calibration:
    """Fit the model of the module docstring to `samples` (read with `offsets`, m per
    drive), starting from `robot`'s file.  ValueError when there are fewer samples than
    needed to fit even the poses."""
    say = progress or (lambda _text: None)
    model, x0 = _offsets_fitted(robot, offsets, samples, say)
    _, basis, scales, _, _, _ = _identifiability(model, model.jacobian(x0), noise)
    # then everything, in the identifiable span of the parameters (scaled)
    x, nfev, converged = _least_squares(model, x0, basis.T / scales[:, None], say, "all parameters")
    J = model.jacobian(x)
    sv, _, _, lines, predicted, good = _identifiability(model, J, noise)
    anchors, attachments, o, s, c, poses = model.unpack(x)
    residuals = model.residuals(x)
    # at rest the cables carry the platform: sum_k t_k u_k = m g in the calibrated frame
    u, *_ = model._terms(x)
    carried = np.einsum("jk,jka->a", -model.forces, u)
    gravity = carried / np.linalg.norm(carried) * float(np.linalg.norm(robot.platform.gravity))
    identifiable = sv[good]
    return Calibration(
        anchors=anchors,
        attachments=attachments,
        offsets=o - s * model.mean_raw,
        drum_radius_scale=s,
        stiffness_scale=1.0 / c,
        gravity=gravity,
        poses=poses,
        residual_rms=float(np.sqrt(np.mean(residuals**2))),
        residual_max=float(np.abs(residuals).max()),
        singular_values=sv,
        condition=float(identifiable.max() / identifiable.min()),
        unidentifiable=lines,
        predicted_std=predicted,
        iterations=nfev,
        converged=converged,
    )


def _least_squares(
    model: _Model, x0: Array, free: Array, say: Progress, what: str
) -> tuple[Array, int, bool]:
    """Minimise the residuals over x0 + free z (free: p x r, parameter change per
    coordinate) and every pose; (the solution, function evaluations, converged)."""
    p, r = model.n_params, free.shape[1]
    evaluations = [0]

    def expand(z: Array) -> Array:
        x = x0.copy()
        x[:p] += free @ z[:r]
        x[p:] += z[r:]
        return x

    def fun(z: Array) -> Array:
        evaluations[0] += 1
        return model.residuals(expand(z))

    def jac(z: Array) -> Array:
        x = expand(z)
        rms = math.sqrt(float(np.mean(model.residuals(x) ** 2)))
        say(f"solving {what}: evaluation {evaluations[0]}, residual RMS {rms * 1e3:.4f} mm")
        Jx = model.jacobian(x)
        return np.hstack([Jx[:, :p] @ free, Jx[:, p:]])

    z0 = np.zeros(r + 6 * model.m)
    solution = least_squares(
        fun, z0, jac=jac, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-12, max_nfev=MAX_NFEV
    )
    return expand(solution.x), int(solution.nfev), bool(solution.success)


def corrected_robot(robot: Robot, calibration: Calibration) -> dict[str, Any]:
    """The robot description (a dict as the robot file holds it) with the calibrated
    anchors, attachments, drum radii, EA and the direction of gravity in its frame."""
    spec = robot.spec.model_dump(exclude_none=True, mode="json")
    spec["gravity"] = [round(float(v), 6) for v in calibration.gravity]
    for k, cable in enumerate(spec["cables"]):
        cable["anchor"] = [round(float(v), 6) for v in calibration.anchors[k]]
        cable["attachment"] = [round(float(v), 6) for v in calibration.attachments[k]]
        actuator = cable.setdefault("actuator", {})
        actuator["drum_radius"] = round(
            float(robot.actuators[k].drum_radius * calibration.drum_radius_scale[k]), 7
        )
        stiffness = robot.actuators[k].cable_stiffness
        if stiffness is not None:
            actuator["cable_stiffness"] = float(f"{stiffness * calibration.stiffness_scale:.5g}")
    return spec


# -- scale -------------------------------------------------------------------------------


@dataclass(frozen=True)
class AnchorDistance:
    """The measured distance (m) between cable `first`'s and cable `second`'s anchor
    points (0-based cable indices, as the robot file lists them): the scale reference."""

    first: int
    second: int
    metres: float


def scaled(calibration: Calibration, distance: AnchorDistance) -> Calibration:
    """`calibration` scaled so that the two anchors of `distance` lie its metres apart.
    Scaling is a gauge freedom of the lengths (a robot and its drums scaled together
    read the same, module docstring): the anchors are scaled about their centroid, the
    attachments about theirs, the poses with them, and the offsets and drum radius scales
    by the same factor; the lengths each pose predicts scale too, every residual with them.
    ValueError when the two anchors coincide in the fit."""
    anchors, attachments = calibration.anchors, calibration.attachments
    fitted = float(np.linalg.norm(anchors[distance.first] - anchors[distance.second]))
    if fitted < 1e-6:
        raise ValueError(
            f"the anchors of cables {distance.first} and {distance.second} coincide in the "
            "fit: measure between two anchors apart"
        )
    factor = distance.metres / fitted
    c, cb = anchors.mean(axis=0), attachments.mean(axis=0)
    poses = [
        Pose.from_matrix(
            c + factor * (pose.position - c) + (factor - 1.0) * pose.rotation @ cb, pose.rotation
        )
        for pose in calibration.poses
    ]
    return replace(
        calibration,
        anchors=c + factor * (anchors - c),
        attachments=cb + factor * (attachments - cb),
        offsets=factor * calibration.offsets,
        drum_radius_scale=factor * calibration.drum_radius_scale,
        poses=poses,
        residual_rms=factor * calibration.residual_rms,
        residual_max=factor * calibration.residual_max,
    )


def scale_cost(robot: Robot, error: float = 0.01, reach: float = 0.3) -> tuple[float, float]:
    """What a common drum radius error `error` (relative) costs a calibration without a
    scale reference, for `robot`'s file: (the farthest anchor's error, the largest error
    of a goto `reach` m from home), both m.  Such a fit is the true robot scaled by
    1 / (1 + error) about the anchors' centroid c (and the attachments' b), so a goto to p
    lands error x |p - c + R b| off."""
    anchors = np.asarray(robot.geometry.anchors, dtype=float)
    attachments = np.asarray(robot.geometry.attachments, dtype=float)
    c = anchors.mean(axis=0)
    home = robot.home
    lever = float(np.linalg.norm(home.position - c + home.rotation @ attachments.mean(axis=0)))
    return error * float(np.linalg.norm(anchors - c, axis=1).max()), error * (lever + reach)


# -- pose selection ---------------------------------------------------------------------


def candidate_poses(
    robot: Robot,
    count: int,
    rng: np.random.Generator,
    reach: Sequence[float] = (0.6, 0.6, 0.45),
    tilt: float = 0.2,
    controller: ControllerSpec | None = None,
) -> list[Pose]:
    """Up to `count` random poses within `reach` (m, per axis) of home and `tilt` (rad)
    of its orientation whose static wrench the cables hold with a margin (every planned
    tension from TENSION_MARGIN x t_min to FORCE_SHARE x force_max) and whose lengths lie
    within the actuators' limits."""
    solver = tension_solver(robot, controller or ControllerSpec())
    home = robot.home
    f_max = float(robot.force_max.min())
    out = []
    for _ in range(count * 5):
        if len(out) == count:
            break
        offset = rng.uniform(-1.0, 1.0, 3) * np.asarray(reach)
        rotvec = rng.uniform(-1.0, 1.0, 3) * tilt / math.sqrt(3.0)
        pose = Pose.from_matrix(home.position + offset, exp_so3(rotvec) @ home.rotation)
        lengths = robot.cable_lengths(pose)
        if robot.length_violations(lengths):
            continue
        zero = np.zeros(robot.n_cables)
        held = solver.solve(robot.jacobian(pose), robot.bias_wrench(pose, np.zeros(6)), zero, zero)
        if not held.feasible:  # outside the wrench-feasible set
            continue
        t = held.tensions
        if t.min() < TENSION_MARGIN * robot.t_min.max() or t.max() > FORCE_SHARE * f_max:
            continue  # near its edge: moving there could leave it
        out.append(pose)
    return out


def _pose_information(robot: Robot, pose: Pose, tensions: Array) -> Array:
    """The pose-eliminated rows (n x p) of one pose at the file's parameters, in the
    parameter coordinates of _Model (offsets per cable, scales about the reading)."""
    lengths, Lam = robot.lengths_and_jacobian(pose)
    n = robot.n_cables
    anchors = np.array(robot.geometry.anchors, dtype=float)
    attachments = np.array(robot.geometry.attachments, dtype=float)
    Pa, Pb = rigid_complement(anchors), rigid_complement(attachments)
    u = Lam[:, :3]
    R = pose.rotation
    Ja = np.zeros((n, 3 * n))
    Jb = np.zeros((n, 3 * n))
    for k in range(n):
        Ja[k, 3 * k : 3 * k + 3] = -u[k]
        Jb[k, 3 * k : 3 * k + 3] = u[k] @ R
    stretch = 1.0 + robot.compliance * tensions
    drum = lengths / stretch
    Jo = -np.diag(stretch)
    Js = -np.diag(drum * stretch) @ rigid_complement_scales(n)  # about zero reading
    Jc = -(drum * robot.compliance * tensions)[:, None]
    J = np.hstack([Ja @ Pa, Jb @ Pb, Jo, Js, Jc])
    q, _ = np.linalg.qr(Lam)
    return J - q @ (q.T @ J)


def select_poses(
    robot: Robot,
    count: int,
    candidates: Sequence[Pose],
    controller: ControllerSpec | None = None,
    start: Pose | None = None,
) -> list[Pose]:
    """`count` of `candidates`, picked greedily for the largest log-determinant of the
    information matrix (D-optimal, columns scaled over the whole set), then ordered
    for a short flight from `start` (default home)."""
    solver = tension_solver(robot, controller or ControllerSpec())
    rows = [_pose_information(robot, p, static_tensions(robot, solver, p)) for p in candidates]
    scales = np.linalg.norm(np.vstack(rows), axis=0)
    scales[scales == 0.0] = 1.0
    rows = [r / scales for r in rows]
    p = rows[0].shape[1]
    M = 1e-9 * np.eye(p)
    chosen: list[int] = []
    for _ in range(min(count, len(candidates))):
        Minv = np.linalg.inv(M)
        best, gain = -1, -math.inf
        for i, r in enumerate(rows):
            if i in chosen:
                continue
            g = np.linalg.slogdet(np.eye(len(r)) + r @ Minv @ r.T)[1]
            if g > gain:
                best, gain = i, g
        chosen.append(best)
        M = M + rows[best].T @ rows[best]
    # nearest neighbour order from the start
    here = (start or robot.home).position
    order, left = [], list(chosen)
    while left:
        nearest = min(left, key=lambda i: float(np.linalg.norm(candidates[i].position - here)))
        order.append(candidates[nearest])
        here = candidates[nearest].position
        left.remove(nearest)
    return order


def rest_samples(
    times: ArrayLike,
    lengths: ArrayLike,
    forces: ArrayLike,
    twists: ArrayLike,
    rest_speed: float = 2e-4,
    rest_turn: float = 2e-3,
    least: float = 0.6,
    average: float = 0.3,
) -> list[Sample]:
    """Samples from a recording (one row per cycle): each stretch where the platform's
    speed stays below `rest_speed` (m/s) and its turn rate below `rest_turn` (rad/s) for
    at least `least` seconds gives one, its last `average` seconds averaged."""
    t = np.asarray(times, dtype=float)
    lengths, forces = np.asarray(lengths, dtype=float), np.asarray(forces, dtype=float)
    twists = np.asarray(twists, dtype=float)
    still = (np.linalg.norm(twists[:, :3], axis=1) < rest_speed) & (
        np.linalg.norm(twists[:, 3:], axis=1) < rest_turn
    )
    still &= np.all(np.isfinite(lengths), axis=1) & np.all(np.isfinite(forces), axis=1)
    samples = []
    k = 0
    while k < len(t):
        if not still[k]:
            k += 1
            continue
        end = k
        while end + 1 < len(t) and still[end + 1]:
            end += 1
        if t[end] - t[k] >= least:
            window = (t >= t[end] - average) & (np.arange(len(t)) <= end) & (t >= t[k])
            samples.append(Sample(lengths[window].mean(axis=0), forces[window].mean(axis=0)))
        k = end + 1
    return samples
