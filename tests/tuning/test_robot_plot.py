"""tuning.robot_plot: the 3-D picture of the robot; its content, checked against the
geometry computed here independently, and the PNG it writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.colors import to_rgba
from scipy.spatial.transform import Rotation

from cdpr import Pose
from tests.conftest import load_robot
from tuning.robot_plot import SLACK_COLOR, SLACK_STYLE, draw_robot_3d, write_robot_3d


def _cables(fig) -> dict[int, object]:
    (ax, *_) = fig.axes
    return {
        int(line.get_gid().split("-")[1]): line
        for line in ax.get_lines()
        if (line.get_gid() or "").startswith("cable-")
    }


def test_each_cable_runs_from_its_anchor_to_its_attachment_coloured_by_tension() -> None:
    robot = load_robot("reference8")
    w, x, y, z = 0.9961947, 0.0, 0.0, 0.0871557  # 10 degrees about z
    pose = Pose((0.1, -0.05, 1.3), (w, x, y, z))
    tensions = np.linspace(30.0, 100.0, robot.n_cables)
    tensions[2] = robot.t_min[2] - 1.0  # below t_min: slack
    tensions[5] = 0.0  # slack
    fig = draw_robot_3d(robot, pose, tensions, path=[[0, 0, 1.2], [0.1, 0, 1.3]])

    cables = _cables(fig)
    assert sorted(cables) == list(range(robot.n_cables))
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    for k, line in cables.items():
        xs, ys, zs = line.get_data_3d()
        ends = np.column_stack([xs, ys, zs])
        anchor = np.array(robot.spec.cables[k].anchor)
        attachment = np.array((0.1, -0.05, 1.3)) + R @ np.array(robot.spec.cables[k].attachment)
        np.testing.assert_allclose(ends, [anchor, attachment], atol=1e-9)
    for k in (2, 5):
        assert cables[k].get_linestyle() == SLACK_STYLE
        assert to_rgba(cables[k].get_color()) == to_rgba(SLACK_COLOR)
    taut = [k for k in range(robot.n_cables) if k not in (2, 5)]
    assert all(cables[k].get_linestyle() == "-" for k in taut)
    low, high = to_rgba(cables[0].get_color()), to_rgba(cables[7].get_color())
    assert low != high and SLACK_COLOR not in (cables[0].get_color(), cables[7].get_color())
    (ax, colorbar) = fig.axes
    assert colorbar.get_ylabel() == "cable tension (N)"
    assert colorbar.get_ylim() == (tensions[0], tensions[7])  # the taut cables' range
    assert [line.get_gid() for line in ax.get_lines()].count("path") == 1


def test_write_robot_3d_writes_a_png(tmp_path: Path) -> None:
    robot = load_robot("reference8")
    file = tmp_path / "robot.png"
    write_robot_3d(file, robot, robot.home, np.full(robot.n_cables, 50.0))
    data = file.read_bytes()
    assert data.startswith(b"\x89PNG") and len(data) > 10_000
