"""The demo's planner: a process of its own that flies one trajectory over zenoh.

    python -m daemon.cli.demo_flight  < {"endpoint": ..., "trajectory": {...}, "settle": s}

`cdprd demo` starts it once the daemon is up; it enables the robot, lets the platform
settle in its hold for `settle` seconds (daemon.cli.demo_cmd.SETTLE), sends the
trajectory through the client module (as any planner would), waits for its end and
prints {"start": ..., "reply": ...} as JSON.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

from cdpr.trajectory import Trajectory, parse_trajectory
from daemon.interface.client import CdprClient
from daemon.process.ordinary import drop_inherited_realtime


def fly(endpoint: str, trajectory: Trajectory, settle: float) -> dict[str, Any]:
    """Enable, hold `settle` seconds, send the trajectory, wait until it no longer tracks."""
    with CdprClient(connect=endpoint, timeout=5.0) as client:
        client.enable()
        time.sleep(settle)
        sent = time.monotonic()
        reply = client.send_trajectory(trajectory)
        deadline = sent + trajectory.duration + 10.0
        while time.monotonic() < deadline:
            if client.status().get("state") != "tracking":
                break
            time.sleep(0.1)
        result = reply.get("result", reply)
        return {"start": float(result.get("start", 0.0)), "reply": reply}


if __name__ == "__main__":
    drop_inherited_realtime()
    request = json.loads(sys.stdin.read())
    trajectory = parse_trajectory(request["trajectory"])
    print(json.dumps(fly(request["endpoint"], trajectory, float(request["settle"]))))
