"""Geometric self-calibration from redundant cable lengths (issue 16 item 4; DESIGN §15
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
motions of the file's attachments (the platform frame).  The scale comes from the drums:
their radius scales keep a mean of 1 (a machined drum's radius is known far better than
a frame measured with a tape; the scales find the drums' differences).

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
from dataclasses import dataclass, field
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
NOISE = 1e-5  # m: length noise assumed for the predicted standard deviations
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
    extra: dict[str, Any] = field(default_factory=dict)

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

    def names(self) -> list[str]:
        """A readable name per parameter coordinate (gauge coordinates by group)."""
        out = []
        for name, sl in self.slices.items():
            size = sl.stop - sl.start
            if name == "offsets":
                out += [f"{name}[{k}]" for k in range(size)]
            elif name == "stiffness":
                out.append("stiffness (EA scale)")
            else:
                out += [f"{name} (gauge coordinate {k})" for k in range(size)]
        return out


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
    """(singular values, right singular vectors of the identifiable span (scaled
    coordinates), column scales, the unidentifiable combinations as text, predicted std
    per group, per-parameter physical directions of the unidentifiable combinations)."""
    reduced = _eliminate_poses(J, model.n_params)
    scales = np.linalg.norm(reduced, axis=0)
    scales[scales == 0.0] = 1.0
    _, sv, vt = np.linalg.svd(reduced / scales, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(len(vt) - len(sv))])  # fewer equations than unknowns
    good = sv > RANK_TOLERANCE * sv.max()
    lines = []
    anchors_dir = model.Pa
    attach_dir = model.Pb
    for k in np.flatnonzero(~good):
        direction = vt[k] / scales
        direction /= np.abs(direction).max()
        parts = []
        for i in np.argsort(-np.abs(direction))[:6]:
            if abs(direction[i]) < 0.2:
                break
            group = _group_of(model, int(i))
            if group == "anchors":
                effect = anchors_dir[:, i - model.slices["anchors"].start].reshape(model.n, 3)
                cables = np.argsort(-np.linalg.norm(effect, axis=1))[:2]
                parts.append("anchors of cables " + ", ".join(map(str, cables)))
            elif group == "attachments":
                effect = attach_dir[:, i - model.slices["attachments"].start].reshape(model.n, 3)
                cables = np.argsort(-np.linalg.norm(effect, axis=1))[:2]
                parts.append("attachments of cables " + ", ".join(map(str, cables)))
            elif group == "stiffness":
                parts.append("the cables' EA")
            elif group == "drum_radius_scale":
                effect = model.Ps[:, i - model.slices[group].start]
                cables = np.argsort(-np.abs(effect))[:2]
                parts.append("drum radii of cables " + ", ".join(map(str, cables)))
            else:
                parts.append(f"{group}[{int(i) - model.slices[group].start}]")
        unique = list(dict.fromkeys(parts))
        lines.append(f"singular value {sv[k]:.2e}: " + " with ".join(unique))
    # predicted covariance in the identifiable span: (V S^-2 V^T) noise^2, unscaled
    V = vt[good].T
    cov = (V / sv[good] ** 2) @ V.T * noise**2
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) / scales
    predicted = {}
    for name, sl in model.slices.items():
        values = std[sl]
        if name == "anchors":
            values = np.abs(model.Pa) @ values  # an anchor coordinate's std, bounded
        elif name == "attachments":
            values = np.abs(model.Pb) @ values
        elif name == "drum_radius_scale":
            values = np.abs(model.Ps) @ values
        predicted[name] = float(values.max())
    return sv, vt[good], scales, lines, predicted, good


def _initial_poses(robot: Robot, offsets: Array, samples: Sequence[Sample]) -> list[Pose]:
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
    offsets = np.asarray(offsets, dtype=float)
    n = robot.n_cables
    if len(samples) < 2:
        raise ValueError(f"calibration needs poses: {len(samples)} given")
    model = _Model(robot, offsets, samples)
    x0 = model.initial(offsets, _initial_poses(robot, offsets, samples))
    say(f"identifiability: {len(samples)} poses, {model.n_params} parameters")
    J = model.jacobian(x0)
    sv, basis, scales, lines, _, _ = _identifiability(model, J, noise)
    p = model.n_params
    # solve in the identifiable span of the parameters (scaled) and every pose
    free = basis.T / scales[:, None]  # p x r: parameter change per identifiable coordinate

    def expand(z: Array) -> Array:
        x = x0.copy()
        x[:p] += free @ z[: free.shape[1]]
        x[p:] += z[free.shape[1] :]
        return x

    r = free.shape[1]
    evaluations = [0]

    def fun(z: Array) -> Array:
        evaluations[0] += 1
        return model.residuals(expand(z))

    def jac(z: Array) -> Array:
        Jx = model.jacobian(expand(z))
        say(
            f"solving: evaluation {evaluations[0]}, residual RMS "
            f"{math.sqrt(np.mean(model.residuals(expand(z)) ** 2)) * 1e3:.4f} mm"
        )
        return np.hstack([Jx[:, :p] @ free, Jx[:, p:]])

    z0 = np.zeros(r + 6 * len(samples))
    solution = least_squares(
        fun, z0, jac=jac, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-12, max_nfev=200
    )
    x = expand(solution.x)
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
        iterations=int(solution.nfev),
        extra={"cables": n},
    )


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
    of its orientation whose static wrench the cables can hold (every tension within
    t_min..force_max) and whose lengths lie within the actuators' limits."""
    solver = tension_solver(robot, controller or ControllerSpec())
    home = robot.home
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
        try:
            tensions = static_tensions(robot, solver, pose)
        except Exception:  # no feasible distribution: outside the wrench-feasible set
            continue
        if not np.all(np.isfinite(tensions)):
            continue
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
