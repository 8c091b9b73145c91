"""The workspace enforced on `cdprd run --sim` as its own processes, over zenoh (loopback,
no scouting): a goto that takes the platform's corners through the floor, one that puts
its body into a table, one where the crossed cables 0 and 6 touch, one with too little
capacity margin, and a trajectory and a path through the touching pose are refused
naming the limit, the waypoint and the corner, obstacle or cables; nothing moves, and a
goto inside the workspace is still flown."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import numpy as np
import pytest
import yaml

from cdpr import Pose
from daemon.interface.client import CdprClient, RequestError
from tests.conftest import OFFSET8
from tests.loopback import free_port
from tests.processes import CONFIG, PREFIX, enabled_sim

pytestmark = [pytest.mark.timeout(150), pytest.mark.slow]

# found inside every other limit (tests/cdpr/test_workspace_check.py)
CROSSED = Pose.from_rotvec((0.076, -0.043, 1.208), (0.042, 0.141, 0.136))
THIN = (0.1, 0.316, 1.927)


def _quaternion(pose: Pose) -> dict[str, float]:
    w, x, y, z = pose.quaternion_tuple
    return {"w": w, "x": x, "y": y, "z": z}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """A simulated daemon, enabled: its zenoh port."""
    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(OFFSET8)  # its crossed pairs clear of each other untilted
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["zenoh"]["prefix"] = PREFIX  # the helpers' (the robot is named reference8-offset)
    data["environment"] = {
        "planes": [{"name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1]}],
        "boxes": [{"name": "table", "min": [-0.3, -0.3, 0.0], "max": [0.3, 0.3, 0.5]}],
    }
    data["workspace"] = {"interference": True}
    config = tmp_path_factory.mktemp("workspace") / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    with enabled_sim(config, port):
        yield port


class Latest:
    """The latest published state (zenoh's thread writes, the test reads)."""

    def __init__(self, client: CdprClient) -> None:
        self.state: dict = {}
        self._subscriber = client.subscribe_state(self._keep)

    def _keep(self, state: dict) -> None:
        self.state = state

    def position(self) -> list[float]:
        deadline = time.monotonic() + 5.0
        while "pose" not in self.state:
            assert time.monotonic() < deadline, "no state with a pose"
            time.sleep(0.05)
        return self.state["pose"]["position"]


def _refused(client: CdprClient, latest: Latest, call) -> RequestError:
    before = latest.position()
    with pytest.raises(RequestError) as refused:
        call()
    time.sleep(0.3)  # a state published after the refusal
    status = client.status()
    assert status["state"] == "hold", status
    assert np.allclose(latest.position(), before, atol=5e-4)  # nothing moved
    return refused.value


def test_the_workspace_refuses_and_names_what_it_refuses(daemon: int) -> None:
    with CdprClient(PREFIX, f"tcp/127.0.0.1:{daemon}", timeout=15.0, name="ws") as client:
        latest = Latest(client)
        floor = _refused(client, latest, lambda: client.goto([0.0, 0.0, 0.10]))
        table = _refused(client, latest, lambda: client.goto([0.0, 0.0, 0.75]))
        crossed = _refused(
            client, latest, lambda: client.goto(CROSSED.position_tuple, _quaternion(CROSSED))
        )
        thin = _refused(client, latest, lambda: client.goto(THIN))
        home = latest.state["pose"]
        through = _refused(
            client,
            latest,
            lambda: client.send_trajectory(
                {
                    "waypoints": [
                        {"t": 0.0, "position": home["position"], "quaternion": home["quaternion"]},
                        {
                            "t": 3.0,
                            "position": list(CROSSED.position_tuple),
                            "quaternion": _quaternion(CROSSED),
                        },
                        {"t": 6.0, "position": home["position"], "quaternion": home["quaternion"]},
                    ]
                }
            ),
        )
        path = _refused(
            client,
            latest,
            lambda: client.send_path(
                {
                    "version": 1,
                    "poses": [
                        {"position": home["position"], "quaternion": home["quaternion"]},
                        {
                            "position": list(CROSSED.position_tuple),
                            "quaternion": _quaternion(CROSSED),
                        },
                    ],
                }
            ),
        )
        reply = client.goto([0.05, 0.0, 1.3])  # inside: flown
        assert reply["accepted"], reply
    assert (
        "workspace_min: platform corner 0 (-0.2, -0.2, -0.3 m in the platform frame)"
        in floor.reason
    )
    # a goto names its target's problem (the table lies on the way to the floor too)
    assert all(r.reason.endswith(" at the target") for r in (floor, table, crossed, thin))
    # the corners at z = 0.45 m, inside the table's 0.5 m top
    assert table.reason.startswith("goto rejected: environment: platform corner 0 ")
    assert "crosses box 'table'" in table.reason
    assert crossed.reason.startswith("goto rejected: workspace.interference: cables 0 and 6 pass")
    assert "closer than their diameters allow (4.0 mm)" in crossed.reason
    # the platform's mass is the payload estimate's (10 kg in the file)
    assert thin.reason.startswith("goto rejected: workspace.margin: the wrench holding the ")
    assert re.search(r"holding the (9\.9\d*|10(\.0\d*)?) kg platform at rest", thin.reason)
    assert "less than workspace.margin 5 N" in thin.reason
    assert "waypoint 0: workspace.interference: cables 0 and 6 pass" in through.reason
    assert "workspace.interference: cables 0 and 6 pass" in path.reason
