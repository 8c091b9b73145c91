"""The daemon config: the examples load, every problem names its key, geometry sanity."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cdpr import ConfigError
from cdpr.description import load_yaml, validate_section
from daemon.cli import main
from daemon.config import FileConfig, RealtimeConfig, load_config, parse_config
from daemon.config.zenoh_config import ZenohSettings

CONFIG = Path(__file__).resolve().parents[2] / "config"


@pytest.mark.parametrize("name", ["reference8-cia402.yaml", "reference8-odrive.yaml"])
def test_examples_load(name: str) -> None:
    config = load_config(CONFIG / name)
    assert config.robot.name == "reference8"
    assert len(config.drives.nodes) == config.robot.n_cables == 8
    assert config.zenoh.listen[0].startswith("tcp/127.0.0.1:")


def test_hardware_template_is_a_valid_file() -> None:
    raw = validate_section(FileConfig, load_yaml(CONFIG / "hardware-template.yaml"), "template")
    assert raw.can.interface == "socketcan" and raw.can.channel == "can0"
    assert raw.drives["brake"] == "holding_brake"
    zenoh = validate_section(ZenohSettings, raw.zenoh, "zenoh")
    assert zenoh.ingress_limits_hz == {"trajectory": 20.0, "cmd/*": 20.0}
    assert raw.realtime == RealtimeConfig(
        priority=50, cpus=None, lock_memory=True, cpu_latency_us=0
    )


def test_realtime_defaults_and_values() -> None:
    """Without the section the core asks for SCHED_FIFO 50, locked memory and the CPUs
    kept awake, on any CPU."""
    assert parse_config(_data(), CONFIG, "test.yaml").realtime == RealtimeConfig(
        priority=50, cpus=None, lock_memory=True, cpu_latency_us=0
    )
    data = _data()
    data["realtime"] = {
        "priority": None, "cpus": [1, 0], "lock_memory": False, "cpu_latency_us": None
    }  # fmt: skip
    held = parse_config(data, CONFIG, "test.yaml").realtime
    assert (held.priority, held.cpus, held.lock_memory) == (None, (1, 0), False)
    assert held.cpu_latency_us is None


def _robot_with(**actuator: float) -> dict:
    robot = yaml.safe_load((CONFIG / "robots" / "reference8.yaml").read_text())
    robot["actuator"].update(actuator)
    return robot


def _data() -> dict:
    return yaml.safe_load((CONFIG / "reference8-cia402.yaml").read_text())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["drives"].update(bogus=1), "bogus"),
        (lambda d: d["drives"].update(nodes=[1, 2, 3]), "3 drives for 8 cables"),
        (lambda d: d["drives"].update(brake="holding_brake"), "has_holding_brake"),
        (lambda d: d["safety"].update(tracking_error_position=-1), "tracking_error_position"),
        (lambda d: d["can"].update(bitrate="fast"), "bitrate"),
        (lambda d: d.update(robot="no/such/robot.yaml"), "cannot read"),
        (lambda d: d["zenoh"].update(listen=["tcp/0.0.0.0:7447"]), "expose"),
        (
            lambda d: d["safety"].update(workspace_min=[-1, -1, 1.5], workspace_max=[1, 1, 2]),
            "outside the workspace box",
        ),
        (
            lambda d: d["drives"].update(
                protocol="odrive", nodes=list(range(8)), feedback_rate_hz=400
            ),
            r"drives.feedback_rate_hz \(400\) is below controller.rate_hz \(500\)",
        ),
        (
            lambda d: d.update(robot=_robot_with(length_max=2.36)),  # home: 2.34 m
            r"robot: cable 0 at the home pose is 2.341 m, outside \[0.3429, 2.319\] m: its "
            "length_min/length_max less the margins",
        ),
        (
            lambda d: d.update(realtime={"priority": 100}),
            r"^test.yaml: realtime.priority: Input should be less than or equal to 99 \(got 100\)$",
        ),
        (
            lambda d: d.update(realtime={"priority": True}),
            r"^test.yaml: realtime.priority: Input should be a valid integer \(got true\)$",
        ),
        (
            lambda d: d.update(realtime={"cpu_latency_us": -1}),
            r"^test.yaml: realtime.cpu_latency_us: Input should be greater than or equal to 0 "
            r"\(got -1\)$",
        ),
        (
            lambda d: d.update(realtime={"cpu_latency_us": 2**31}),
            r"^test.yaml: realtime.cpu_latency_us: Input should be less than or equal to "
            r"2147483647 \(got 2147483648\)$",
        ),
        (
            lambda d: d.update(realtime={"cpus": []}),
            r"^test.yaml: realtime.cpus: an empty list: give CPU indices, or null for any CPU$",
        ),
        (
            lambda d: d.update(realtime={"cpus": [3, 1, 3, 1, 2]}),
            r"^test.yaml: realtime.cpus: CPU 1, 3 listed more than once$",
        ),
        (
            lambda d: d.update(realtime={"cpus": [0, -1]}),
            r"^test.yaml: realtime.cpus.1: Input should be greater than or equal to 0 \(got -1\)$",
        ),
        (
            lambda d: d.update(realtime={"lock_memory": "yes"}),
            r"^test.yaml: realtime.lock_memory: Input should be a valid boolean \(got 'yes'\)$",
        ),
        (lambda d: d.update(realtime={"rtprio": 50}), r"^test.yaml: realtime.rtprio: Extra"),
        (
            lambda d: d["safety"].update(max_cable_speed=1.5),
            r"safety.max_cable_speed: 1.5 m/s must exceed the fastest cable rate the "
            r"trajectory limits allow \(1.82 m/s",
        ),
    ],
)
def test_problems_name_the_key(change, message: str) -> None:
    data = _data()
    change(data)
    with pytest.raises(ConfigError, match=message):
        parse_config(data, CONFIG, "test.yaml")


@pytest.mark.parametrize(
    ("safety", "words"),
    [
        (
            {"tilt_max": 0.04, "tracking_error_orientation": 0.05},
            r"safety: tilt_max \(0.04 rad\) leaves no room .* tracking_error_orientation \(0.05",
        ),
        (
            {"workspace_min": [-1.5, -1.5, 1.24], "tracking_error_position": 0.02},
            r"home position .* outside the workspace box \(workspace_min/workspace_max.*shrunk "
            r"by tracking_error_position \(0.02 m\).*position z = 1.2500 m outside \[1.2601",
        ),
        (
            {"workspace_max": [0.03, 1.5, 2.5], "tracking_error_position": 0.05},
            r"shrunk by tracking_error_position \(0.05 m\).*position x = 0.0000 m outside",
        ),
    ],
)
def test_margins_that_leave_trajectories_no_room_are_refused(safety: dict, words: str) -> None:
    """Trajectories must stay inside the box and tilt less the tracking-error bounds: a
    config where that excludes the home pose is refused, naming the keys."""
    data = _data()
    data["safety"].update(safety)
    with pytest.raises(ConfigError, match=words):
        parse_config(data, CONFIG, "test.yaml")


def test_the_example_margins_leave_room() -> None:
    config = parse_config(_data(), CONFIG, "test.yaml")
    inner = config.reference_limits
    assert inner.lower[2] == pytest.approx(0.02, abs=1e-4)  # the floor less 2 cm
    assert inner.tilt_max == pytest.approx(0.55, abs=1e-3)  # 0.6 rad less 0.05 rad
    assert config.pose_limits.tilt_max == 0.6


def test_check_config_summarises_a_daemon_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(CONFIG / "reference8-cia402.yaml")]) == 0
    out = capsys.readouterr().out
    assert "drives: cia402 nodes [1, 2, 3, 4, 5, 6, 7, 8]" in out
    assert "zenoh: prefix cdpr/reference8" in out


def test_check_config_fails_with_the_problem(tmp_path: Path, capsys) -> None:
    data = _data()
    data["drives"]["protocol"] = "canopen-ish"
    data["robot"] = str(CONFIG / "robots" / "reference8.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    assert main(["check-config", str(bad)]) == 1
    assert "protocol" in capsys.readouterr().err


# -- the view: section (the live 3-D view) ------------------------------------------------


@pytest.mark.parametrize(
    ("view", "message"),
    [
        (
            {"enabled": True, "host": "0.0.0.0"},
            r"^test.yaml: view: the host '0.0.0.0' is not on loopback; serving the live view "
            r"on a network is an explicit choice: set view.expose: true, or use 127.0.0.1$",
        ),
        ({"port": 70000}, r"^test.yaml: view.port: Input should be less than or equal to 65535"),
        ({"rate_hz": 0}, r"^test.yaml: view.rate_hz: Input should be greater than 0 \(got 0\)$"),
        ({"rate_hz": 1000}, r"^test.yaml: view.rate_hz: Input should be less than or equal to 200"),
        ({"host": "ws://x:1"}, r"^test.yaml: view.host: 'ws://x:1' is not a host name or address"),
        ({"enabled": "yes"}, r"^test.yaml: view.enabled: Input should be a valid boolean"),
        ({"colour": "red"}, r"^test.yaml: view.colour: Extra inputs are not permitted"),
        (
            {"allowed_origins": ["https://app.foxglove.dev/"]},
            r"^test.yaml: view.allowed_origins: 'https://app.foxglove.dev/' is not a web "
            r"origin: scheme://host\[:port\] in lower case, no path",
        ),
        (
            {"allowed_origins": ["*"]},
            r"^test.yaml: view.allowed_origins: '\*' is not a web origin",
        ),
        (
            {"allowed_hosts": ["robot.lab:8765"]},
            r"^test.yaml: view.allowed_hosts: 'robot.lab:8765' is not a host name or address",
        ),
    ],
)
def test_view_problems_name_the_key(view: dict, message: str) -> None:
    data = _data()
    data["view"] = view
    with pytest.raises(ConfigError, match=message):
        parse_config(data, CONFIG, "test.yaml")


def test_the_view_is_off_and_on_loopback_unless_asked() -> None:
    view = parse_config(_data(), CONFIG, "test.yaml").view
    assert (view.enabled, view.host, view.port, view.rate_hz) == (False, "127.0.0.1", 8765, 30.0)
    assert view.allowed_origins == ("https://app.foxglove.dev",)  # Foxglove's web app only
    assert view.gate_hosts == ("127.0.0.1", "localhost")
    data = _data()
    data["view"] = {"enabled": True, "host": "0.0.0.0", "expose": True, "port": 0}
    view = parse_config(data, CONFIG, "test.yaml").view
    assert (view.enabled, view.host, view.port) == (True, "0.0.0.0", 0)


def test_a_ros2_ingress_limit_and_raw_downsampling_are_exclusive() -> None:
    data = _data()
    rule = {"key_expr": "a", "freq": 1.0}
    data["zenoh"] = {
        "config": {"downsampling": [{"flows": ["ingress"], "messages": ["put"], "rules": [rule]}]}
    }
    data["ros2"] = {"enabled": True, "ingress_limit_hz": 5}
    with pytest.raises(ConfigError, match=r"^test.yaml: ros2.ingress_limit_hz: .*use one of them$"):
        parse_config(data, CONFIG, "test.yaml")
    del data["ros2"]["ingress_limit_hz"]
    assert parse_config(data, CONFIG, "test.yaml").ros2.ingress_limit_hz is None


def test_ros2_router_is_a_client_session_of_its_own_beside_the_daemons() -> None:
    """`ros2: {enabled: true, router: tcp/127.0.0.1:7447}` is the one line that joins a
    ROS 2 graph: the bridge reaches rmw_zenohd's port as a client (a router relays
    between its clients and the graph's peers; between two peers only with gossip, which
    stays off), while the daemon's session listens on its own port (7448) unchanged; a
    router off loopback is refused as zenoh.connect's would be."""
    example = CONFIG / "reference8-cia402.yaml"
    router = "tcp/127.0.0.1:7447"
    joined = load_config(example, lambda d: d.update(ros2={"enabled": True, "router": router}))
    assert joined.ros2_router is not None
    assert (joined.ros2_router.mode, joined.ros2_router.connect) == ("client", (router,))
    assert joined.ros2_router.listen_endpoints == ()
    assert joined.zenoh.connect == ()
    assert joined.zenoh.listen_endpoints == ("tcp/127.0.0.1:7448",)
    off = load_config(example, lambda d: d.update(ros2={"enabled": False, "router": router}))
    assert off.ros2_router is None
    lease = {"link": {"tx": {"lease": 5000}}}  # the daemon's transport settings go along
    both = {"ros2": {"enabled": True, "router": router}}

    def with_transport(d: dict) -> None:
        d.update(both)
        d["zenoh"]["config"] = {"transport": lease, "adminspace": {"enabled": False}}

    tuned = load_config(example, with_transport)
    assert tuned.ros2_router is not None and tuned.ros2_router.config == {"transport": lease}
    far = {"enabled": True, "router": "tcp/10.0.0.5:7447"}
    with pytest.raises(ConfigError) as refused:
        load_config(example, lambda d: d.update(ros2=far))
    assert "ros2.router (a client session of the ROS 2 bridge's own)" in str(refused.value)
    assert "'tcp/10.0.0.5:7447' is not on loopback" in str(refused.value)
