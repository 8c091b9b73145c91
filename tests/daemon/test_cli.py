"""The cdprd command line: check-config summarises a sound file, names problems in a bad one."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from daemon.cli import main
from tests.conftest import ROBOTS
from tests.loopback import free_port


def test_check_config_summarises_a_robot(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(ROBOTS / "reference8.yaml")]) == 0
    out = capsys.readouterr().out
    assert "robot reference8: 8 cables, platform 10 kg" in out
    assert "modal masses at home (Lemma 1, kg): 2.41" in out


def test_check_config_fails_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROBOTS / "reference8.yaml").read_text().replace("mass: 10.0", "mass: -10.0")
    (tmp_path / "r.yaml").write_text(text)
    assert main(["check-config", str(tmp_path / "r.yaml")]) == 1
    assert "platform.mass: Input should be greater than 0 (got -10.0)" in capsys.readouterr().err


# -- hostile and careless configs: one line each, never a traceback ---

CONFIG = ROBOTS.parent
EXAMPLE = (CONFIG / "reference8-cia402.yaml").read_text()
ROBOT = (ROBOTS / "reference8.yaml").read_text()


def example(*changes: tuple[str, str], inline_robot: bool = False) -> str:
    """The cia402 example with text replacements; its robot file inline if asked."""
    robot = f"robot: {ROBOTS / 'reference8.yaml'}"
    if inline_robot:
        body = "".join(f"  {line}\n" if line.strip() else "\n" for line in ROBOT.splitlines())
        robot = f"robot:\n{body}"
    text = EXAMPLE.replace("robot: robots/reference8.yaml", robot)
    for old, new in changes:
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


ZERO_LENGTH = (  # cable 0's anchor where its attachment is at the home pose (0, 0, 1.25)
    "{anchor: [1.50, 1.50, 2.50], attachment: [0.20, -0.20, 0.30]}",
    "{anchor: [0.20, -0.20, 1.55], attachment: [0.20, -0.20, 0.30]}",
)
ODRIVE = (CONFIG / "reference8-odrive.yaml").read_text()
ODRIVE = ODRIVE.replace("robot: robots/reference8.yaml", f"robot: {ROBOTS / 'reference8.yaml'}")
BRAKES = "  has_holding_brake: true"
assert BRAKES in ODRIVE
NAMED = {  # case: (file content, the problem each error line names after 'error: FILE: ')
    "an ODrive robot without brakes": (
        ODRIVE.replace(BRAKES, "  has_holding_brake: false"),
        "drives.has_holding_brake: an ODrive robot needs holding brakes: ODrive firmware 0.6 "
        "disarms an axis (IDLE, motor unpowered) on every axis error",
    ),
    "accept_fall_on_axis_error for CiA 402": (
        example(("  protocol: cia402", "  protocol: cia402\n  accept_fall_on_axis_error: true")),
        "drives: accept_fall_on_axis_error applies to protocol odrive only",
    ),
    "not UTF-8": (b"# r\xe9glages\n" + EXAMPLE.encode(), "line 1: not UTF-8 text (byte 0xe9"),
    "5000-deep lists": (
        example() + "extra: " + "[" * 5000 + "]" * 5000 + "\n",
        "nested deeper than 64 levels",
    ),
    "5000-deep mappings": (
        example() + "extra: " + "{a: " * 5000 + "1" + "}" * 5000 + "\n",
        "nested deeper than 64 levels",
    ),
    "5000-digit integer": (
        example(("rate_hz: 500", "rate_hz: " + "9" * 5000)),
        "integer of 5000 digits is out of range (64 bits)",
    ),
    "a zero-length cable": (
        example(ZERO_LENGTH, inline_robot=True),
        "robot: cables.0: the cable has zero length at the home pose",
    ),
    "an unknown sim key": (
        example(("  plant:\n", "  plant_typo: 1\n  plant:\n")),
        "sim.plant_typo: Extra inputs are not permitted (got 1)",
    ),
    "a plant mismatch of the wrong size": (
        example(("step: 0.001\n", "step: 0.001\n    mismatch: {anchor_offsets: [[0, 0, 0]]}\n")),
        "sim.plant: mismatch.anchor_offsets: 1 entries for 8 cables",
    ),
    "watchdog_timeout: true": (
        example(("watchdog_timeout: 0.05", "watchdog_timeout: true")),
        "drives.watchdog_timeout: Input should be a valid number (got true)",
    ),
    "max_residual: true": (
        example(("max_residual: 2.0e-3", "max_residual: true"), inline_robot=True),
        "robot.forward_kinematics.max_residual: Input should be a valid number (got true)",
    ),
    "string node ids": (
        example(("nodes: [1, 2,", 'nodes: ["1", 2,')),
        "drives.nodes.0: Input should be a valid integer (got '1')",
    ),
    "rate_hz: 8:20": (
        example(("rate_hz: 500", "rate_hz: 8:20")),
        "controller.rate_hz: Input should be a valid number (got '8:20')",
    ),
    "yes as a boolean": (
        example(("  brake: position_hold", "  has_holding_brake: yes\n  brake: position_hold")),
        "drives.has_holding_brake: Input should be a valid boolean (got 'yes')",
    ),
    "a float for an integer": (
        example(("stale_cycles: 25", "stale_cycles: 25.0")),
        "safety.stale_cycles: Input should be a valid integer (got 25.0)",
    ),
    "a string for a number": (
        example(("bitrate: 1000000", 'bitrate: "1000000"')),
        "can.bitrate: Input should be a valid integer (got '1000000')",
    ),
    "direction: true": (
        example(("direction: 1 ", "direction: true ")),
        "drives.direction: Input should be the integer 1 or -1, or a valid array (got true)",
    ),
    "a key given twice": (
        example(("rate_hz: 500", "rate_hz: 500\n  rate_hz: 100")),
        "duplicate key 'rate_hz'",
    ),
    "a lone surrogate": (
        example(("level: info", 'level: "info\\ud800"')),
        "a lone surrogate escape (\\ud800-\\udfff) is not a character",
    ),
    "a huge quaternion part": (
        example(("quaternion: {w: 1.0,", "quaternion: {w: 1.0e+300,"), inline_robot=True),
        "robot.home.quaternion: quaternion norm is 1e+300; a unit quaternion is required",
    ),
    "a robot file that is /dev/zero": (
        example((f"robot: {ROBOTS / 'reference8.yaml'}", "robot: /dev/zero")),
        "robot: /dev/zero: cannot read: a device, not a regular file",
    ),
    "a file over 1 MiB": (example() + "#" * (1 << 20) + "\n", "cannot read: longer than"),
    "a kd too high for a home mode": (  # unstable with no command delay at all
        example(("kd: 20.0", "kd: 200.0")),
        "controller: mode 4 at home (modal mass 5.88 kg) is unstable at 500 Hz with pid kp 100 "
        "ki 50 kd 200 and drives.force_lag 2 ms: the single-actuator loop is stable for "
        "masses up to 5.47 kg only; change the gains",
    ),
    "the 500 Hz gains at 100 Hz": (  # stable only while commands act within 3.96 ms
        example(("rate_hz: 500", "rate_hz: 100"), ("timeout: 0.05", "timeout: 0.02")),
        "controller: mode 6 at home (modal mass 9.49 kg) goes unstable at 100 Hz with pid kp "
        "100 ki 50 kd 20 and drives.force_lag 2 ms when commands act 3.96 ms after their "
        "sample; the daemon's commands act up to 5 ms after it",
    ),
}


@pytest.mark.parametrize("case", NAMED)
def test_check_config_names_file_key_and_problem_in_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    content, problem = NAMED[case]
    path = tmp_path / "cdprd.yaml"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: ") and problem in line, line


def test_check_config_takes_an_odrive_robot_with_brakes_or_an_accepted_fall(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "cdprd.yaml"
    accepted = "  has_holding_brake: false\n  accept_fall_on_axis_error: true"
    for text in (ODRIVE, ODRIVE.replace(BRAKES, accepted)):
        path.write_text(text)
        assert main(["check-config", str(path)]) == 0, capsys.readouterr().err
        assert "drives: odrive nodes [0, 1, 2, 3, 4, 5, 6, 7]" in capsys.readouterr().out


@pytest.mark.parametrize("kind", ["device", "directory", "pipe"])
def test_check_config_refuses_a_path_that_is_not_a_regular_file(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """/dev/zero used to be read until MemoryError, a named pipe until a writer came."""
    path = {"device": Path("/dev/zero"), "directory": tmp_path, "pipe": tmp_path / "fifo"}[kind]
    if kind == "pipe":
        os.mkfifo(path)
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: cannot read: a ") and "not a regular file" in line


def cdprd(*args: str) -> subprocess.Popen[str]:
    """`python -m daemon.cli ARGS` from this checkout, stdout and stderr captured."""
    command = [sys.executable, "-m", "daemon.cli", *args]
    pipe = subprocess.PIPE
    return subprocess.Popen(command, cwd=CONFIG.parent, stdout=pipe, stderr=pipe, text=True)


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
@pytest.mark.timeout(120)
def test_run_refuses_what_check_config_refuses_with_the_same_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cases = ["not UTF-8", "an unknown sim key", "rate_hz: 8:20", "an ODrive robot without brakes"]
    cases += ["a plant mismatch of the wrong size", "the 500 Hz gains at 100 Hz"]
    runs = []
    for i, case in enumerate(cases):
        content = NAMED[case][0]
        path = tmp_path / f"cdprd{i}.yaml"
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        assert main(["check-config", str(path)]) == 1
        runs.append((case, capsys.readouterr().err, cdprd("run", "--sim", "--config", str(path))))
    for case, expected, proc in runs:
        _out, err = proc.communicate(timeout=60)
        assert proc.returncode == 1 and err == expected, f"{case}: {err}"


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
@pytest.mark.timeout(120)
def test_run_with_its_zenoh_port_taken_exits_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", free_port()))
        taken.listen()
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        path = tmp_path / "cdprd.yaml"
        path.write_text(example(("tcp/127.0.0.1:7448", endpoint)))
        assert main(["check-config", str(path)]) == 0  # it explains the clash first
        clash = capsys.readouterr().out.splitlines()[-1]
        proc = cdprd("run", "--sim", "--config", str(path))
        _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    # the start-up's INFO lines (real-time, drives up), then one line saying what failed
    lines = [line for line in err.splitlines() if " INFO " not in line]
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith(f"error: {path}: zenoh.listen: {endpoint}: cannot open the zenoh")
    assert "Address already in use" in line
    assert clash.startswith(f"zenoh: {endpoint} is taken on this host now: `cdprd run` would")
    assert main(["check-config", str(path)]) == 0  # the port free again: no such line
    assert " is taken on this host" not in capsys.readouterr().out


def test_check_config_says_where_the_ros2_node_joins_and_whether_the_router_is_up(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with socket.socket() as router:
        router.bind(("127.0.0.1", free_port()))
        endpoint = f"tcp/127.0.0.1:{router.getsockname()[1]}"
        path = tmp_path / "cdprd.yaml"
        path.write_text(example() + f"ros2: {{enabled: true, router: {endpoint}}}\n")
        assert main(["check-config", str(path)]) == 0
        down = capsys.readouterr().out.splitlines()[-1]
        router.listen()
        assert main(["check-config", str(path)]) == 0
        up = capsys.readouterr().out.splitlines()[-1]
    joins = f"ros2: node cdprd on the ROS 2 graph's router {endpoint}"
    assert down == f"{joins} (nothing listens there now: it joins when it does)"
    assert up == joins


# -- the CiA 402 drive profile at config load ----------------------------------

DEFAULT_EDS = CONFIG / "can" / "cia402_cst.eds"


def eds_without(*objects: str) -> str:
    """The simulated drive's EDS without the sections of `objects` ("1016", "1400sub5")."""
    kept, skip = [], False
    for line in DEFAULT_EDS.read_text().splitlines(keepends=True):
        if line.startswith("["):
            name = line.strip()[1:-1].upper()
            skip = any(name == o.upper() or name.startswith(o.upper() + "SUB") for o in objects)
        if not skip:
            kept.append(line)
    return "".join(kept)


DEADLINES = tuple(f"140{k}sub5" for k in range(4))
PROFILE = "  heartbeat_timeout: 0.35\n  profile: {eds: vendor/drive.eds}\n"


def test_check_config_prints_what_each_drive_does_when_the_daemon_dies(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["check-config", str(CONFIG / "reference8-cia402.yaml")]) == 0
    out = capsys.readouterr().out
    assert f"drive profile: EDS {DEFAULT_EDS}" in out
    # the EDS has RPDO deadlines 0x14xx:05: the host turns them off (drivers.cia402.profile)
    assert (
        "drive watchdog (when the daemon dies): consumer heartbeat 0x1016 on node 127, 58 ms "
        "-> quick stop (0x6007 = 3), then holds in QUICK STOP ACTIVE (0x605A = 6)"
    ) in out
    assert (
        "host heartbeat: every 6 ms (node 127); a drive notices a dead daemon within 58 ms"
    ) in out
    # per drive, the bound: force_max 600 N / (m0 1.9 kg + 10 kg) = 50.4 m/s^2; the cable
    # rate 1 m/s + 2 rad/s x 0.41 m = 1.82 m/s; over 58 ms, 84.8 + 105.8 mm
    assert (
        "drift before a drive notices (s = 0.5 a t^2 + v t, a = force_max / (m0 + platform "
        "mass); limit 200 mm):\n"
    ) in out
    for k in range(8):
        assert (
            f"  cable {k} (node {k + 1}): 190.6 mm = 0.5 x 50.4 m/s^2 x (58 ms)^2 + 1.82 m/s "
            "x 58 ms\n"
        ) in out


SLOW_CONSUMER = "  consumer_heartbeat_time: 0.35\n"


def test_check_config_refuses_a_watchdog_that_lets_a_cable_drift_too_far(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The vendor EDS has no RPDO deadline: a 350 ms consumer heartbeat (the old default)
    lets each cable run on under its last torque for 350 ms, 3.7 m by the bound; refused
    with the drive and the numbers named.  Allowed once the limit says so."""
    (tmp_path / "vendor").mkdir()
    (tmp_path / "vendor" / "drive.eds").write_text(eds_without(*DEADLINES))
    path = tmp_path / "cdprd.yaml"
    path.write_text(example(("  heartbeat_timeout: 0.35\n", SLOW_CONSUMER + PROFILE)))
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        f"error: {path}: safety.max_watchdog_drift: a dead daemon goes unnoticed for 350 ms, "
        "in which cable 0 (node 1): 3726.9 mm = 0.5 x 50.4 m/s^2 x (350 ms)^2 + 1.82 m/s x "
        "350 ms under the last torque (s = 0.5 a t^2 + v t, a = force_max / (m0 + platform "
        "mass)), more than the 200 mm allowed: shorten drives.consumer_heartbeat_time (and "
        "host_heartbeat_period), or, where it is not set, drives.watchdog_timeout"
    )
    path.write_text(
        example(
            ("  heartbeat_timeout: 0.35\n", SLOW_CONSUMER + PROFILE),
            ("safety:\n", "safety:\n  max_watchdog_drift: 4.0\n"),
        )
    )
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "(when the daemon dies): consumer heartbeat 0x1016 on node 127, 350 ms -> " in out
    assert "  cable 7 (node 8): 3726.9 mm = 0.5 x 50.4 m/s^2 x (350 ms)^2" in out


UNSAFE = {  # objects missing from the drive's EDS: the problem check-config names
    # RPDO deadlines do not count: the host sends no RPDO every cycle in every state
    "no watchdog": (("1016",), "has no consumer heartbeat 0x1016 (the host sets no RPDO"),
    "no 0x6007": (("6007",), "has no abort connection option 0x6007"),
    "no 0x605A": (("605A",), "no quick stop option code 0x605A and the drives have no holding"),
}


@pytest.mark.parametrize("case", UNSAFE)
def test_check_config_refuses_a_drive_a_dead_daemon_leaves_free_wheeling(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The EDS is named relative to the config file (taken from its folder, not the
    working directory)."""
    missing, problem = UNSAFE[case]
    (tmp_path / "vendor").mkdir()
    (tmp_path / "vendor" / "drive.eds").write_text(eds_without(*missing))
    path = tmp_path / "cdprd.yaml"
    path.write_text(example(("  heartbeat_timeout: 0.35\n", PROFILE)))
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: drives.profile.eds: drive.eds ") and problem in line


def test_check_config_refuses_an_rpdo_deadline_the_host_cannot_switch_off(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A read-only RPDO deadline is refused when its default is non-zero (the drive would
    stop at the first switch between hold and torque control), accepted at 0."""
    text = DEFAULT_EDS.read_text()
    section = text.index("[1401sub5]")
    read_only = text[:section] + text[section:].replace("AccessType=rw", "AccessType=ro", 1)
    after = read_only[section:].replace("DefaultValue=0", "DefaultValue=50", 1)
    fixed = read_only[:section] + after
    for name, eds in (("zero", read_only), ("fixed", fixed)):  # EDS files are cached by path
        (tmp_path / name / "vendor").mkdir(parents=True)
        (tmp_path / name / "vendor" / "drive.eds").write_text(eds)
        (tmp_path / name / "cdprd.yaml").write_text(
            example(("  heartbeat_timeout: 0.35\n", PROFILE))
        )
    assert main(["check-config", str(tmp_path / "zero" / "cdprd.yaml")]) == 0
    capsys.readouterr()
    path = tmp_path / "fixed" / "cdprd.yaml"
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        f"error: {path}: drives.profile.eds: drive.eds: RPDO2's deadline 0x1401:05 is ro "
        "at 50 ms: the host cannot switch it off, and it sends no RPDO every cycle in every "
        "state (map another RPDO)"
    )


def test_a_drive_without_quick_stop_hold_needs_its_holding_brake(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "vendor").mkdir()
    (tmp_path / "vendor" / "drive.eds").write_text(eds_without("605A"))
    path = tmp_path / "cdprd.yaml"
    braked = "  brake: holding_brake\n  has_holding_brake: true\n"
    path.write_text(
        example(("  heartbeat_timeout: 0.35\n", PROFILE), ("  brake: position_hold", braked))
    )
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"drive profile: EDS {tmp_path / 'vendor' / 'drive.eds'}" in out
    assert "-> quick stop (0x6007 = 3), power stage off, holding brake engaged" in out


@pytest.mark.parametrize(
    ("profile", "problem"),
    [
        ("{eds: nowhere.eds}", "drives.profile.eds: cannot read EDS "),
        (
            "{sdo_writes: [{object: '0x605A', value: 2}]}",
            "drives.profile.sdo_writes.0: 0x605A:00 (Quick stop option code) = 2: the host "
            "sets this object itself",
        ),
        (
            "{rpdo: [{number: 1, objects: [0x6040, 0x6071], transmission_type: 255}]}",
            "drives.profile.rpdo: no RPDO maps 0x6040 + 0x6071 + 0x6060 together",
        ),
    ],
)
def test_the_profile_is_checked_when_the_config_loads(
    profile: str, problem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "cdprd.yaml"
    path.write_text(
        example(
            ("  heartbeat_timeout: 0.35\n", f"  heartbeat_timeout: 0.35\n  profile: {profile}\n")
        )
    )
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: {problem}"), line


@pytest.mark.timeout(30)
def test_an_eds_that_is_a_fifo_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """canopen opened the EDS itself: a FIFO there blocked the check (and start-up)."""
    os.mkfifo(tmp_path / "x.eds")
    path = tmp_path / "cdprd.yaml"
    eds = "  heartbeat_timeout: 0.35\n  profile: {eds: x.eds}\n"
    path.write_text(example(("  heartbeat_timeout: 0.35\n", eds)))
    assert main(["check-config", str(path)]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line == (
        f"error: {path}: drives.profile.eds: cannot read EDS {tmp_path / 'x.eds'}: "
        "a FIFO (named pipe), not a regular file"
    )
