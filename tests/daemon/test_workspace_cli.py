"""`cdprd workspace` and check-config's workspace line: the map computed, summarised,
saved where the config says, drawn (PNG) and shown (a Foxglove scene in an MCAP read back
with the mcap reader); a stale map is named and not used; a home pose outside the
workspace is refused."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from cdpr.so3 import quat_to_matrix
from cdpr.workspace_map import WorkspaceMap
from daemon.cli import main
from tests.conftest import OFFSET8, ROBOTS

CONFIG = ROBOTS.parent / "reference8-cia402.yaml"


def _config(tmp_path: Path, environment: dict | None = None, **workspace: object) -> Path:
    data = yaml.safe_load(CONFIG.read_text())
    if environment is not None:
        data["environment"] = environment
    data["robot"] = str(OFFSET8)  # its crossed pairs clear of each other untilted
    data["state_dir"] = str(tmp_path / "state")
    data["workspace"] = {"step": 0.2, "tilt": 0.2, "interference": True, **workspace}
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_robot_file_s_workspace_as_json_saved_where_asked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output = tmp_path / "r8.workspace"
    args = ["workspace", "--config", str(OFFSET8), "--step", "0.25"]
    options = ["--tilt", "0.2", "--payload-max", "3", "--interference", "--json"]
    assert main([*args, *options, "--output", str(output)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["orientations"] == 9 and out["saved"] == str(output)
    settings = {"step": 0.25, "tilt": 0.2, "payload": [0.0, 3.0], "margin": 5.0}
    assert out["settings"] == {**settings, "interference": True}
    assert 0.0 < out["volume_per_orientation_m3"][0] <= out["points"] / 9 * 0.25**3
    assert out["worst_margin_n"] >= 5.0 and out["reasons"]["interference"] > 0
    saved = WorkspaceMap.load(output)
    assert saved.fingerprint == out["fingerprint"]


def test_a_daemon_config_s_map_goes_to_its_state_dir_and_check_config_uses_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _config(tmp_path)
    assert main(["check-config", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("workspace:"))
    assert "no map at" in line and "computed on a 20 cm grid" in line
    assert main(["workspace", "--config", str(path)]) == 0
    text = capsys.readouterr().out
    saved = tmp_path / "state" / "reference8-offset.workspace"
    assert f"saved to {saved}" in text and "home:" in text and "at every orientation" in text
    assert main(["check-config", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("workspace:"))
    assert line.startswith("workspace: margin >= 5 N at rest, cables' interference refused; ")
    assert re.search(r"; \S+ m\^3 at home, \S+ m\^3 \(\d+% of the box\) at every tilt, ", line)
    assert line.endswith(f"(map {saved})")
    # a coarser map of the same workspace is still the config's
    assert main(["workspace", "--config", str(path), "--step", "0.25", "--tilt", "0.1"]) == 0
    capsys.readouterr()
    assert main(["check-config", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("workspace:"))
    assert line.endswith(f"(map {saved})")
    # the robot's margin asked for changes: the map is stale, named, and not used
    _config(tmp_path, margin=6.0)
    assert main(["check-config", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("workspace:"))
    assert f"the map at {saved} is stale" in line and "computed on a 20 cm grid" in line


def test_the_slices_and_the_scene_are_written(tmp_path: Path, capsys) -> None:
    """The MCAP holds the boundary, the anchors, the box obstacle and both planes (the
    floor and a slanted wall), each as a thin square turned onto its plane."""
    png, scene = tmp_path / "ws.png", tmp_path / "ws.mcap"
    wall = np.array([-0.6, -0.8, 0.0])
    environment = {
        "planes": [
            {"name": "floor", "point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
            {"name": "wall", "point": [3.0, 3.0, 0.0], "normal": wall.tolist()},
        ],
        "boxes": [{"name": "table", "min": [-0.3, 1.0, 0.0], "max": [0.3, 1.4, 0.5]}],
    }
    config = _config(tmp_path, environment)
    args = ["workspace", "--config", str(config), "--step", "0.15"]
    assert main([*args, "--png", str(png), "--mcap", str(scene)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    with scene.open("rb") as stream:  # decoded by mcap_protobuf from the file's own schema
        messages = list(
            make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        )
    assert [(m.channel.topic, m.schema.name) for m in messages] == [
        ("/cdpr/scene", "foxglove.SceneUpdate")
    ]
    cubes = {entity.id: len(entity.cubes) for entity in messages[0].decoded_message.entities}
    assert cubes["workspace"] > 10
    entities = {entity.id: entity for entity in messages[0].decoded_message.entities}
    assert len(entities["environment"].spheres) == 8  # the frame's anchors
    table, floor, slanted = entities["environment"].cubes
    assert (table.size.x, table.size.y, table.size.z) == pytest.approx((0.6, 0.4, 0.5))
    for square, normal, offset in ((floor, (0.0, 0.0, 1.0), 0.0), (slanted, wall, -4.2)):
        assert square.size.z == pytest.approx(0.002) and square.size.x > 1.0
        q = square.pose.orientation
        turned = quat_to_matrix([q.w, q.x, q.y, q.z]) @ (0.0, 0.0, 1.0)
        assert turned == pytest.approx(normal, abs=1e-9)
        centre = np.array([square.pose.position.x, square.pose.position.y, square.pose.position.z])
        assert centre.dot(normal) == pytest.approx(offset)


@pytest.mark.parametrize(
    "option, problem",
    [
        (("--step", "-1"), "error: --step: -1 must be a positive number"),
        (("--margin", "nan"), "error: --margin: nan must be a number >= 0"),
    ],
)
def test_bad_options_are_named(option, problem, tmp_path: Path, capsys) -> None:
    assert main(["workspace", "--config", str(_config(tmp_path)), *option]) == 1
    assert capsys.readouterr().err.strip() == problem


def test_a_home_pose_with_too_little_margin_is_refused_by_check_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _config(tmp_path, margin=500.0)
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: workspace.margin: at the home pose the wrench ")
    assert "less than workspace.margin 500 N, which trajectories must keep" in line


def test_interference_is_refused_unless_the_config_turns_it_off(tmp_path: Path, capsys) -> None:
    """On by default: reference8's idealised crossed pairs meet at home, which check-config
    refuses naming the cables; its shipped configs turn it off, and --no-interference
    maps without it."""
    data = yaml.safe_load(CONFIG.read_text())
    assert data["workspace"] == {"interference": False}
    del data["workspace"]
    data["robot"] = str(ROBOTS / "reference8.yaml")
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["check-config", str(path)]) == 1
    error = capsys.readouterr().err
    assert "workspace.interference: at the home pose cables 0 and 6 pass 0.0 mm apart" in error
    args = ["workspace", "--config", str(path), "--step", "0.25", "--tilt", "0.2", "--json"]
    assert main([*args, "--no-interference"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["settings"]["interference"] is False and out["reasons"]["interference"] == 0
    assert out["volume_per_orientation_m3"][0] > 0.0
