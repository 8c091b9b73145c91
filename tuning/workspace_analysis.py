"""Workspace analysis (`cdprd analyze`): modal masses and the modes they predict.

The paper's Assertion: along each eigenvector sigma_i of N = M^-1 Lambda^T Lambda the
robot's small-signal error obeys the single-actuator closed loop with effective mass
m_i = 1 / eig_i(N) in [m0, inf] (Lemma 1).  So the robot's modes at a pose are those of
tuning.analysis.Rig.loop with m = m_i, and gains that keep the rig stable for every
m from m0 up to the largest modal mass of the workspace work everywhere (claim 1).

The rig uses the first cable's actuator, the robot's cable stiffness (EA), a cable as
long as the robot's mean cable at home and a preload equal to the mean static tension
the controller plans there.  What it lacks is the stiffness the cables' internal
tension gives the platform (internal_stiffness): model_at = measured cancels it through
the cables and actuators (exactly only when they are fast against it), model_at =
reference leaves it in the loop.  Each analysed pose reports it per unit modal mass, to
be compared with the controller's own stiffness (k_p for a PID).

Latency tolerance: how late the drives may apply a command, after the sample it answers,
before the rig goes unstable at some mass between the lightest and the heaviest modal
mass found.  The cable's elastic mode (tens of Hz) is what delay destabilises.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import eigh

from cdpr import Pose, Robot, retract
from cdpr.control_spec import ControllerSpec
from cdpr.controller import static_tensions, tension_solver
from cdpr.tension import TensionSolver
from sim_bus.plant.config import CableConfig, PlantConfig
from tuning.analysis import LoopModes, Rig

Array = NDArray[np.float64]
Progress = Callable[[int, int], None]  # (done, total)

SKIP_REASONS = ("rank", "lengths", "tensions")  # why a grid pose is not analysed
SWEEP_END = 1e4  # kg: the robustness sweep covers [m0, SWEEP_END]
LATENCY_MASSES = 24  # masses log-spaced over the modal masses found, for the latency scan
_ZERO6 = np.zeros(6)


class ModalBasis(NamedTuple):
    """Lemma 1 at one pose: N = M^-1 Lambda^T Lambda = sum_i sigma_i pi_i / m_i."""

    masses: Array  # m_i ascending (kg); inf where Lambda^T Lambda is singular
    vectors: Array  # 6 x 6, column i = sigma_i (tangent coordinates, sigma_i^T M sigma_i = 1)
    duals: Array  # 6 x 6, row i = pi_i with pi_i . sigma_j = delta_ij

    def coordinates(self, theta: Array) -> Array:
        """Modal coordinates pi_i . theta of tangent vectors theta (..., 6)."""
        return np.asarray(theta, dtype=float) @ self.duals.T


def modal_basis(robot: Robot, pose: Pose) -> ModalBasis:
    """The eigenvectors of M^-1 Lambda^T Lambda and their modal masses at `pose`."""
    M = robot.mass_matrix(pose)
    Lam = robot.jacobian(pose)
    lam, V = eigh(Lam.T @ Lam, M)  # ascending; V^T M V = I
    lam, V = lam[::-1], V[:, ::-1]  # heaviest mode last
    with np.errstate(divide="ignore"):
        masses = np.where(lam > 1e-12 * max(float(lam[0]), 1e-300), 1.0 / lam, np.inf)
    return ModalBasis(masses, V, V.T @ M)


def internal_stiffness(robot: Robot, pose: Pose, tensions: Array, step: float = 1e-6) -> Array:
    """K = d(Lambda^T t) / d theta at constant tensions t (6 x 6, central differences):
    the stiffness the cables' internal tension alone gives the platform; a restoring
    direction has a positive diagonal entry (the cables' wrench is -Lambda^T t)."""
    K = np.empty((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = step
        ahead = robot.jacobian(retract(pose, e)).T @ tensions
        behind = robot.jacobian(retract(pose, -e)).T @ tensions
        K[:, j] = (ahead - behind) / (2.0 * step)
    return K


class PredictedMode(NamedTuple):
    """The single-actuator loop with effective mass m_i: the robot's mode i."""

    mass: float  # kg
    stable: bool
    frequency_hz: float  # natural frequency |s| / 2 pi of the dominant (slowest) pole
    damping: float  # damping ratio -Re(s) / |s| of the dominant pole
    resonance_hz: float  # the least-damped oscillatory pole (nan: none)
    resonance_damping: float
    settling_time: float  # s, 2 % band after a step (inf: never)
    overshoot: float  # fraction of the step
    poles: Array  # finite continuous-time poles (1/s), slowest first


def predicted_mode(loop: LoopModes) -> PredictedMode:
    """Summarise Rig.loop's result: dominant pole, resonance, step figures."""
    poles = loop.poles[np.isfinite(loop.poles)]
    s = poles[0]
    oscillatory = poles[poles.imag > 1e-9]
    if oscillatory.size:
        zeta = -oscillatory.real / np.abs(oscillatory)
        r = oscillatory[int(np.argmin(zeta))]
        res_hz, res_zeta = abs(r) / (2 * math.pi), float(-r.real / abs(r))
    else:
        res_hz = res_zeta = math.nan
    return PredictedMode(
        loop.mass,
        loop.stable,
        abs(s) / (2 * math.pi),
        float(-s.real / abs(s)) if abs(s) > 0 else math.nan,
        res_hz,
        res_zeta,
        loop.settling_time,
        loop.overshoot,
        poles,
    )


def rig_for(
    robot: Robot,
    spec: ControllerSpec,
    config: PlantConfig | None = None,
    force_lag: float | None = None,
) -> Rig:
    """The rig for `robot` under `spec`'s gains and period; `config` (default: the
    simulator's, with the robot's cable stiffness when it declares one) sets the
    actuator model, cable and encoders; `force_lag` (s: a daemon's drives.force_lag)
    replaces the actuator model's first-order lag."""
    actuator = robot.actuators[0]
    if config is None:
        config = PlantConfig()
        if actuator.cable_stiffness is not None:
            cable = CableConfig(stiffness=actuator.cable_stiffness, damping=config.cable.damping)
            config = config.model_copy(update={"cable": cable})
    if force_lag is not None:
        model = config.actuator.model_copy(update={"c": [force_lag]})
        config = config.model_copy(update={"actuator": model})
    tensions = static_tensions(robot, tension_solver(robot, spec), robot.home)
    return Rig(
        actuator,
        spec.linear_controller(),
        spec.period,
        spec.discretisation,
        config,
        float(np.mean(robot.cable_lengths(robot.home))),
        float(np.mean(tensions)),
    )


class PoseAnalysis(NamedTuple):
    """One pose: skipped (reason, detail) or its modal masses and predicted modes."""

    pose: Pose
    reason: str  # "" when analysed, else one of SKIP_REASONS
    detail: str  # what made it infeasible
    masses: Array  # modal masses, ascending (empty when skipped)
    modes: tuple[PredictedMode, ...]
    internal_stiffness: Array  # per mode, pi_i M^-1 K sigma_i (1/s^2), K at the static tensions

    @property
    def feasible(self) -> bool:
        return not self.reason


def analyse_pose(robot: Robot, rig: Rig, tension: TensionSolver, pose: Pose) -> PoseAnalysis:
    """Modal masses, predicted modes and internal stiffness at `pose` held at rest; a
    pose with a rank-deficient Lambda, a cable length out of range or no feasible static
    tensions is skipped with the reason."""
    lengths, Lam = robot.lengths_and_jacobian(pose)
    sv = np.linalg.svd(Lam, compute_uv=False)
    if sv[-1] < 1e-6 * sv[0]:
        return _skipped(pose, "rank", f"Lambda singular values {np.round(sv, 4).tolist()}")
    violations = robot.length_violations(lengths)
    if violations:
        return _skipped(pose, "lengths", "; ".join(violations))
    zero = np.zeros(robot.n_cables)
    static = tension.solve(Lam, robot.bias_wrench(pose, _ZERO6), zero, zero)
    if not static.feasible:
        return _skipped(pose, "tensions", static.reason)
    basis = modal_basis(robot, pose)
    K = internal_stiffness(robot, pose, static.tensions)
    M = robot.mass_matrix(pose)
    per_mass = np.einsum("ij,ji->i", basis.duals, np.linalg.solve(M, K @ basis.vectors))
    modes = tuple(predicted_mode(rig.loop(float(m))) for m in basis.masses)
    return PoseAnalysis(pose, "", "", basis.masses, modes, per_mass)


def _skipped(pose: Pose, reason: str, detail: str) -> PoseAnalysis:
    return PoseAnalysis(pose, reason, detail, np.empty(0), (), np.empty(0))


class WorkspaceGrid(NamedTuple):
    """Positions on a regular grid (home orientation) and what each gave."""

    low: Array  # grid corner (m)
    high: Array
    points_per_axis: int
    points: tuple[PoseAnalysis, ...]

    @property
    def feasible(self) -> list[PoseAnalysis]:
        return [p for p in self.points if p.feasible]

    @property
    def skipped(self) -> dict[str, int]:
        """Skipped poses per reason (every reason listed)."""
        return {r: sum(p.reason == r for p in self.points) for r in SKIP_REASONS}

    @property
    def mass_range(self) -> tuple[float, float]:
        """Smallest and largest modal mass over the analysed poses (nan, nan: none)."""
        masses = [p.masses for p in self.feasible]
        if not masses:
            return math.nan, math.nan
        allm = np.concatenate(masses)
        return float(allm.min()), float(allm.max())


def grid_box(robot: Robot, shrink: float = 0.5) -> tuple[Array, Array]:
    """The box spanned by the anchors and the home position, scaled by `shrink` about
    home, so that it contains home (for a suspended robot, whose anchors share one
    height, z runs from home up towards them)."""
    if not 0.0 < shrink <= 1.0:
        raise ValueError(f"shrink must be in (0, 1], got {shrink}")
    home = robot.home.position
    anchors = robot.geometry.anchors
    low = np.minimum(anchors.min(axis=0), home)
    high = np.maximum(anchors.max(axis=0), home)
    return home - shrink * (home - low), home + shrink * (high - home)


def workspace_grid(
    robot: Robot,
    rig: Rig,
    tension: TensionSolver,
    points_per_axis: int,
    shrink: float = 0.5,
    progress: Progress | None = None,
) -> WorkspaceGrid:
    """analyse_pose at points_per_axis^3 positions filling grid_box(robot, shrink)."""
    if points_per_axis < 2:
        raise ValueError(f"points_per_axis must be at least 2, got {points_per_axis}")
    low, high = grid_box(robot, shrink)
    axes = [np.linspace(lo, hi, points_per_axis) for lo, hi in zip(low, high, strict=True)]
    positions = list(itertools.product(*axes))
    q = robot.home.quaternion
    out = []
    for k, p in enumerate(positions):
        out.append(analyse_pose(robot, rig, tension, Pose(np.array(p), q)))
        if progress is not None:
            progress(k + 1, len(positions))
    return WorkspaceGrid(low, high, points_per_axis, tuple(out))


class Robustness(NamedTuple):
    """The rig over effective masses m0 ... sweep_end (log-spaced), and the edge of the
    stable range that starts at m0 (refined by bisection)."""

    sweep: tuple[LoopModes, ...]
    largest_stable_mass: float | None  # every m in [m0, this] is stable; None: m0 is not
    stable_to_sweep_end: bool

    @property
    def sweep_end(self) -> float:
        return self.sweep[-1].mass

    def covers(self, mass: float) -> bool:
        """Are the gains stable for every effective mass from m0 up to `mass`?"""
        edge = self.largest_stable_mass
        return edge is not None and mass <= edge


def robustness(rig: Rig, sweep_end: float = SWEEP_END, points: int = 60) -> Robustness:
    """Sweep the rig's effective mass from m0 to `sweep_end`; bisect the first loss of
    stability to 0.1 %."""
    sweep = rig.sweep(sweep_end, points)
    edge, to_end = stable_range(rig, sweep_end, points, [loop.stable for loop in sweep])
    return Robustness(tuple(sweep), edge, to_end)


def stable_range(
    rig: Rig, sweep_end: float = SWEEP_END, points: int = 60, verdicts: list[bool] | None = None
) -> tuple[float | None, bool]:
    """Robustness's edge without its sweep's step responses (the daemon's check): the
    largest mass m such that the rig is stable at every log-spaced mass from m0 up to m
    (the first loss bisected to 0.1 %; None: m0 is not), and whether that is the sweep's
    end.  `verdicts`: the sweep's stability when known, else rig.stable up to the first
    unstable mass."""
    masses = np.geomspace(rig.actuator.m0, sweep_end, points)
    stable = iter(verdicts) if verdicts is not None else (rig.stable(float(m)) for m in masses)
    first_unstable = next((k for k, ok in enumerate(stable) if not ok), None)
    if first_unstable is None:
        return float(masses[-1]), True
    if first_unstable == 0:
        return None, False
    lo, hi = float(masses[first_unstable - 1]), float(masses[first_unstable])
    while hi / lo > 1.001:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if rig.stable(mid) else (lo, mid)
    return lo, False


class LatencyTolerance(NamedTuple):
    """How late the commands may take effect (after the sample they answer) before the
    rig goes unstable at one of the masses checked: the cables' elastic mode turns
    with the delay's phase, and heavy modal masses put it lowest."""

    masses: Array  # the effective masses checked (kg)
    seconds: float | None  # every latency in [0, seconds] is stable; None: not even 0
    limiting_mass: float | None  # the mass that goes unstable just beyond; None: none
    searched_to: float  # s: stable up to here when limiting_mass is None

    def periods(self, period: float) -> float | None:
        return None if self.seconds is None else self.seconds / period


def latency_tolerance(
    rig: Rig, masses: Array, most_periods: float = 4.0, step: float = 0.05
) -> LatencyTolerance:
    """Scan the latency from 0 in `step` periods up to `most_periods` periods and bisect
    the first loss of stability at any of `masses` to 0.1 % of a period."""
    masses = np.sort(np.asarray(masses, dtype=float))[::-1]  # heavy ones fail first
    period = rig.period

    def unstable_at(latency: float) -> float | None:
        return next((float(m) for m in masses if not rig.stable(float(m), latency)), None)

    searched_to = most_periods * period
    failing = unstable_at(0.0)
    if failing is not None:
        return LatencyTolerance(masses, None, failing, 0.0)
    good = 0.0
    for k in range(1, round(most_periods / step) + 1):
        bad = k * step * period
        failing = unstable_at(bad)
        if failing is None:
            good = bad
            continue
        while bad - good > 1e-3 * period:
            mid = 0.5 * (good + bad)
            at_mid = unstable_at(mid)
            if at_mid is None:
                good = mid
            else:
                bad, failing = mid, at_mid
        return LatencyTolerance(masses, good, failing, searched_to)
    return LatencyTolerance(masses, searched_to, None, searched_to)


class Analysis(NamedTuple):
    """Everything `cdprd analyze` reports for one robot and controller."""

    robot: str
    spec: ControllerSpec
    rig: Rig
    home: PoseAnalysis
    grid: WorkspaceGrid
    robustness: Robustness
    latency: LatencyTolerance  # over the modal masses found (home and grid)

    @property
    def largest_modal_mass(self) -> float:
        """Over home and the analysed grid poses (kg; nan when none was analysed)."""
        masses = _modal_masses_found(self.home, self.grid)
        return float(masses.max()) if masses.size else math.nan

    @property
    def covers_workspace(self) -> bool:
        """Claim 1: the gains are stable for every modal mass found (home and grid)."""
        largest = self.largest_modal_mass
        return not math.isnan(largest) and self.robustness.covers(largest)


def analyse(
    robot: Robot,
    spec: ControllerSpec,
    points_per_axis: int = 5,
    shrink: float = 0.5,
    config: PlantConfig | None = None,
    progress: Progress | None = None,
    force_lag: float | None = None,
) -> Analysis:
    """The whole analysis (see module docstring); `progress(done, total)` follows the grid;
    `force_lag`: rig_for's (a daemon config's drives.force_lag)."""
    rig = rig_for(robot, spec, config, force_lag)
    tension = tension_solver(robot, spec)
    home = analyse_pose(robot, rig, tension, robot.home)
    grid = workspace_grid(robot, rig, tension, points_per_axis, shrink, progress)
    found = _modal_masses_found(home, grid)
    m0 = rig.actuator.m0  # the lightest any modal mass can be (Lemma 1)
    masses = np.geomspace(m0, max(m0, *found[np.isfinite(found)]), LATENCY_MASSES)
    return Analysis(
        robot.name, spec, rig, home, grid, robustness(rig), latency_tolerance(rig, masses)
    )


def _modal_masses_found(home: PoseAnalysis, grid: WorkspaceGrid) -> Array:
    """Every modal mass of home and the analysed grid poses (kg)."""
    found = [p.masses for p in (home, *grid.points) if p.feasible]
    return np.concatenate(found) if found else np.empty(0)
