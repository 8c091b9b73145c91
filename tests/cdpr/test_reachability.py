"""cdpr.path.reachability: TOPP-RA's passes, compiled, held to the `toppra` package (the
authors' implementation, its Seidel solver, its interpolation scheme built here from the
points' rows) as the independent reference: the same controllable sets, speeds and
accelerations on the daemon's own paths (their tension, speed and acceleration rows,
both timing passes), on seeded random rows with degenerate ones, and the same place
where a path cannot be held."""

from __future__ import annotations

import numpy as np
import pytest
import toppra
import toppra.algorithm
import toppra.constraint

from cdpr.path import Path, PathPoint, parse_gcode, parse_path
from cdpr.path import timing as path_timing
from cdpr.path.geometry import BlendedPath
from cdpr.path.reachability import load_factor, parameterize
from cdpr.wrench_margin import wrench_length
from tests.daemon_stack import config_for
from tuning.scenarios import STANDARD_SET

toppra.setup_logging("WARNING")
Q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}


class _Stages(toppra.constraint.LinearConstraint):
    """The points' rows (a, b, c, X) as toppra's canonical linear constraint at each
    stage, in its interpolation scheme: point i's rows, and point i + 1's at the same u
    with x + 2 ds u (the last stage repeats its own)."""

    def __init__(self, a, b, c, X) -> None:
        super().__init__()
        self.points = (a, b, c, X)
        self.identical = True

    def compute_constraint_params(self, path, gridpoints, *args, **kwargs):
        a, b, c, X = self.points
        twice = 2.0 * np.diff(gridpoints)[:, None]
        A = np.hstack([a, np.vstack([a[1:] + twice * b[1:], a[-1:]])])
        B = np.hstack([b, np.vstack([b[1:], b[-1:]])])
        C = np.hstack([c, np.vstack([c[1:], c[-1:]])])
        width = A.shape[1]
        return A, B, C, np.eye(width), np.zeros(width), None, X


def _toppra(points, grid):
    """toppra's (u, speeds, K) from rest to rest; its path only scales (here by 1)."""
    line = toppra.SplineInterpolator(grid, np.column_stack([grid, grid]))
    problem = toppra.algorithm.TOPPRA(
        [_Stages(*points)], line, gridpoints=grid, solver_wrapper="seidel"
    )
    return problem.compute_parameterization(0.0, 0.0, return_data=True)


def _motions(path: Path, config):
    """(rows, grid) of each motion of `path` as the daemon times it: the first pass
    (no damping) and the second (the winches' damping at the first pass's speeds)."""
    robot, limits, timing = config.robot, config.trajectory, path_timing.Timing()
    length = wrench_length(robot.geometry.attachments)
    for motion in path_timing._motions(path, length):
        geometry = BlendedPath([p.pose for p in motion], [p.blend for p in motion], length)
        grid = path_timing._grid(geometry, timing)
        caps = path_timing._speed_caps(geometry, motion, grid, limits)
        model = path_timing._GridModel.of(geometry, grid, robot)
        rows = path_timing._Rows(model, robot, limits, timing.margin, caps)
        damping = np.zeros(len(grid))
        for _ in range(2):
            points = (rows.a, rows.b, rows.constant(damping), rows.xbound)
            yield points, grid
            damping = parameterize(*points, grid).speed


def _same(ours, theirs, grid, durations: bool = True) -> None:
    """Our parameterization is toppra's: its controllable sets, squared speeds and
    accelerations, and with `durations` the time the motion takes.  Where rounding
    leaves a forward step no acceleration, toppra lowers x by 1e-10 at a time (up to
    1e-6 relative on the figure-eight) and this module by doubling steps; near rest the
    two then pick x = 3e-10 or 3e-8."""
    u, speed, _, K = theirs
    np.testing.assert_allclose(ours.K, K, rtol=0.0, atol=1e-9 * np.abs(K).max())
    assert ours.failed == -1
    x, x_ours = speed**2, ours.speed**2
    np.testing.assert_allclose(x_ours, x, rtol=0.0, atol=1e-5 * x.max())
    np.testing.assert_allclose(ours.u, u, rtol=0.0, atol=1e-3 * np.abs(u).max())
    if durations:

        def duration(s):
            return float(np.sum(2.0 * np.diff(grid) / (s[:-1] + s[1:])))

        assert duration(ours.speed) == pytest.approx(duration(speed), rel=1e-5)


def _paths(config) -> dict[str, Path]:
    robot = config.robot
    figure = [w.pose for w in STANDARD_SET["figure_eight"](robot).waypoints]
    blends = [0.0] + [0.05] * (len(figure) - 2) + [0.0]
    square = {
        "poses": [
            {"position": [0.0, 0.0, 1.25], "quaternion": Q},
            {"position": [0.3, 0.0, 1.25], "blend": 0.05},
            {"position": [0.3, 0.3, 1.35], "blend": 0.05},
            {"position": [0.0, 0.3, 1.25], "speed": 0.2},
        ]
    }
    star = "G21 G90 F20000\n" + "\n".join(
        f"G1 X{150 * np.cos(k * 2.5):.1f} Y{150 * np.sin(k * 2.5):.1f}" for k in range(12)
    )
    return {
        "figure_eight": Path(
            tuple(PathPoint(p, blend=b) for p, b in zip(figure, blends, strict=True))
        ),
        "square": parse_path(square, config.trajectory),
        "gcode_star": parse_gcode(star, robot.home, 0.01, config.trajectory),
    }


@pytest.mark.parametrize("name", ["figure_eight", "square", "gcode_star"])
def test_the_daemons_paths_are_timed_as_toppra_times_them(name: str) -> None:
    config = config_for("cia402")
    checked = 0
    for points, grid in _motions(_paths(config)[name], config):
        _same(parameterize(*points, grid), _toppra(points, grid), grid)
        checked += 1
    assert checked >= 2  # both passes of every motion


def test_random_stages_with_degenerate_rows_give_toppras_sets() -> None:
    """Seeded random rows around a feasible rest (c < 0), with rows on x alone, rows
    on u alone, repeated rows and rows far from binding: the same controllable sets and
    time law as toppra's (not the same durations: random rows brake some stages to
    speeds of 1e-5, where the time taken is all rounding)."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        n, m = int(rng.integers(5, 60)), int(rng.integers(3, 40))
        A = rng.normal(size=(n + 1, m))
        B = rng.normal(size=(n + 1, m))
        C = -rng.uniform(0.05, 2.0, size=(n + 1, m))
        A[:, 0] = 0.0  # x alone
        B[:, 1] = 0.0  # u alone
        A[:, 2], B[:, 2], C[:, 2] = A[:, 3], B[:, 3], C[:, 3]  # a repeated row
        C[:, -1] = -1e6  # never binding
        X = np.column_stack([np.zeros(n + 1), rng.uniform(0.5, 5.0, n + 1)])
        grid = np.concatenate([[0.0], np.cumsum(rng.uniform(0.01, 0.2, n))])
        points = (A, B, C, X)
        _same(parameterize(*points, grid), _toppra(points, grid), grid, durations=False)


def test_a_path_the_cables_cannot_hold_fails_where_toppras_sets_end() -> None:
    """Up to a point beside an anchor (tests/cdpr/test_path.py): the stage where no speed
    is controllable is the one where toppra's controllable sets turn NaN."""
    config = config_for("cia402")
    anchor = config.robot.geometry.anchors[0]
    data = {
        "poses": [
            {"position": [0.0, 0.0, 1.25], "quaternion": Q},
            {"position": (0.9 * anchor + [0.0, 0.0, -0.05]).tolist()},
        ]
    }
    points, grid = next(_motions(parse_path(data), config))
    ours = parameterize(*points, grid)
    _, speed, _, K = _toppra(points, grid)
    assert speed is None
    assert ours.failed >= 0
    assert np.isnan(ours.speed).all()
    assert np.isnan(K[ours.failed]).all() and not np.isnan(K[ours.failed + 1 :]).any()


def test_the_load_factor_is_the_largest_share_of_a_row_s_room() -> None:
    """load_factor against numpy on random rows, some with C >= 0 (never binding at
    rest: left out), and 0 where no row has room to share."""
    rng = np.random.default_rng(11)
    A, B, C = (rng.normal(size=(50, 30)) for _ in range(3))
    u, x = rng.normal(size=50), rng.uniform(0.0, 2.0, 50)
    need = (A * u[:, None] + B * x[:, None]) / -C
    assert load_factor(A, B, C, u, x) == pytest.approx(need[C < 0.0].max(), rel=1e-15)
    assert load_factor(A, B, np.abs(C), u, x) == 0.0
