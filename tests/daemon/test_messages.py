"""The zenoh interface's JSON messages: strict decoding, clear errors, versioned encoding."""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr import Pose
from cdpr.trajectory import SCHEMA_VERSION, TrajectoryLimits
from daemon.interface.messages import (
    VERSION_KEY,
    decode_command,
    decode_json,
    decode_trajectory,
    encode,
    error_body,
    reply_error,
    reply_ok,
    request_id,
)
from daemon.service.api import COMMANDS, CommandError

LIMITS = TrajectoryLimits(max_waypoints=50)
IDENTITY = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}


def waypoint(t: float, z: float = 1.25, quaternion: dict | None = None) -> dict:
    return {"t": t, "position": [0.0, 0.0, z], "quaternion": quaternion or IDENTITY}


def trajectory(**extra: object) -> dict:
    return {"version": 1, "waypoints": [waypoint(0.0), waypoint(2.0, 1.35)], **extra}


def refusal(fn: Callable[..., object], *args: object) -> CommandError:
    with pytest.raises(CommandError) as info:
        fn(*args)
    return info.value


def test_schema_version_is_the_trajectory_one_under_one_key() -> None:
    assert VERSION_KEY == "version"
    assert SCHEMA_VERSION == 1
    for message in (reply_ok("status", {}), reply_error("goto", CommandError("busy", "x"))):
        assert message[VERSION_KEY] == SCHEMA_VERSION


def test_a_valid_trajectory_decodes_with_id_and_start() -> None:
    request = decode_trajectory(trajectory(id="plan-1", start=1.7e9), LIMITS)
    assert request.id == "plan-1" and request.start == 1.7e9
    assert request.trajectory.duration == 2.0
    assert decode_trajectory(trajectory(), LIMITS).start is None  # "now" by default
    assert decode_trajectory(trajectory(start="now"), LIMITS).id is None


@pytest.mark.parametrize(
    ("payload", "words"),
    [
        (b"[1, 2", "invalid JSON"),
        (b'{"t": NaN}', "NaN is not a JSON number"),
        (b"[Infinity]", "Infinity is not a JSON number"),
        (b"[-Infinity]", "-Infinity is not a JSON number"),
        (b"\xff\xfe{}", "not UTF-8"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b" " * 2048, "exceeds the limit of 1024 bytes"),
    ],
)
def test_bad_json_is_refused_naming_the_problem(payload: bytes, words: str) -> None:
    error = refusal(decode_json, payload, 1024 if len(payload) == 2048 else 1 << 20)
    assert error.code == "bad_request"
    assert words in error.reason


@pytest.mark.parametrize(
    ("data", "code", "words"),
    [
        ([], "bad_request", "expected a JSON object, got list"),
        (trajectory(version=2), "bad_request", "unsupported schema version 2"),
        (trajectory(version="1"), "bad_request", "unsupported schema version '1'"),
        (trajectory(id=""), "bad_request", "id: expected a string"),
        (trajectory(id="x" * 129), "bad_request", "id: expected a string"),
        (trajectory(start="later"), "bad_request", 'start: expected "now"'),
        (trajectory(start=-5), "bad_request", "not a unix time"),
        (trajectory(start=10**400), "bad_request", "not a unix time"),
        (trajectory(colour="red"), "bad_request", "unknown key(s) 'colour'"),
        ({"waypoints": "abc"}, "bad_request", "waypoints: expected a list"),
        (
            {"waypoints": [waypoint(0.0), {**waypoint(1.0), "t": "1"}]},
            "bad_request",
            "waypoints[1].t: expected a number, got str",
        ),
        (
            {"waypoints": [waypoint(0.0), {**waypoint(1.0), "position": [0, 0]}]},
            "bad_request",
            "waypoints[1].position",
        ),
        (
            {"waypoints": [waypoint(0.0), {**waypoint(1.0), "speed": 2}]},
            "bad_request",
            "unknown key(s) 'speed'",
        ),
        (
            {"waypoints": [waypoint(0.0), {**waypoint(1.0), "quaternion": [1, 0, 0, 0]}]},
            "bad_request",
            "never a bare array",
        ),
        (
            {"waypoints": [waypoint(0.0), waypoint(2.0), waypoint(1.0)]},
            "rejected",
            "times",
        ),
        (
            {"waypoints": [waypoint(0.0), waypoint(1.0, quaternion={**IDENTITY, "w": 1.1})]},
            "rejected",
            "unit quaternion",
        ),
        (
            {"waypoints": [waypoint(float(t)) for t in range(51)]},
            "rejected",
            "51 waypoints exceed the limit of 50",
        ),
        ({"waypoints": [waypoint(0.0), waypoint(10**400)]}, "rejected", "not a finite number"),
    ],
)
def test_bad_trajectories_are_refused_naming_the_problem(
    data: object, code: str, words: str
) -> None:
    error = refusal(decode_trajectory, data, LIMITS)
    assert error.code == code
    assert words in error.reason


def test_trajectory_errors_name_the_limit_the_waypoint_and_the_field() -> None:
    data = {"waypoints": [waypoint(0.0), waypoint(1.0, quaternion={**IDENTITY, "x": 0.5})]}
    body = error_body(refusal(decode_trajectory, data, LIMITS))
    assert body["code"] == "rejected"
    assert body["limit"] == "unit_quaternion"
    assert body["waypoint"] == 1
    assert body["field"] == "waypoints[1].quaternion"
    assert body["value"] == pytest.approx(math.sqrt(1.25))


def test_request_id_is_read_even_from_a_rejected_message() -> None:
    assert request_id({"id": "abc", "waypoints": 3}) == "abc"
    assert request_id({"id": 3}) is None
    assert request_id([1]) is None


def test_commands_take_no_arguments_but_goto_and_brake() -> None:
    for name in COMMANDS:
        if name != "goto":
            assert decode_command(name, {}) == {}
            assert decode_command(name, {"version": 1}) == {}
    assert decode_command("brake", {"reason": "operator"}) == {"reason": "operator"}
    args = decode_command("goto", {"position": {"x": 0.1, "y": 0.0, "z": 1.2}})
    assert args["pose"] == Pose((0.1, 0.0, 1.2))
    q = {"w": math.cos(0.25), "x": 0.0, "y": 0.0, "z": math.sin(0.25)}
    args = decode_command("goto", {"position": [0, 0, 1], "quaternion": q})
    assert np.allclose(args["pose"].quaternion, [q["w"], 0, 0, q["z"]])


@pytest.mark.parametrize(
    ("name", "data", "code", "words"),
    [
        ("jump", None, "unknown_command", "unknown command 'jump'"),
        ("enable", {"force": True}, "bad_request", "unknown key(s) 'force'"),
        ("status", [], "bad_request", "expected a JSON object, got list"),
        ("disable", None, "bad_request", "disable: expected a JSON object, got null"),
        ("hold", 0, "bad_request", "hold: expected a JSON object, got int"),
        ("brake", "stop", "bad_request", "brake: expected a JSON object, got str"),
        ("reset", [], "bad_request", "reset: expected a JSON object, got list"),
        ("status", {"version": 3}, "bad_request", "unsupported schema version 3"),
        ("brake", {"reason": "x" * 201}, "bad_request", "brake.reason"),
        ("goto", {}, "bad_request", "missing key 'position'"),
        ("goto", {"position": [0, 0]}, "bad_request", "expected [x, y, z]"),
        ("goto", {"position": [0, 0, "1"]}, "bad_request", "position[2]: expected a number"),
        ("goto", {"position": [0, 0, True]}, "bad_request", "position[2]: expected a number"),
        ("goto", {"position": [0, 0, 10**400]}, "bad_request", "not a finite number"),
        ("goto", {"position": {"x": 0, "y": 0}}, "bad_request", "needs x, y and z"),
        ("goto", {"position": [0, 0, 1], "speed": 1}, "bad_request", "unknown key(s) 'speed'"),
        ("goto", {"position": [0, 0, 1], "quaternion": [1, 0, 0, 0]}, "bad_request", "object"),
        (
            "goto",
            {"position": [0, 0, 1], "quaternion": {**IDENTITY, "w": 2.0}},
            "rejected",
            "unit quaternion",
        ),
    ],
)
def test_bad_commands_are_refused_naming_the_problem(
    name: str, data: object, code: str, words: str
) -> None:
    error = refusal(decode_command, name, data)
    assert error.code == code
    assert words in error.reason


def test_encoding_is_strict_json_with_numpy_and_non_finite_values() -> None:
    payload = encode({"a": np.array([1.0, np.nan]), "b": np.float64(np.inf), "c": (1, 2)})
    assert json.loads(payload) == {"a": [1.0, None], "b": None, "c": [1, 2]}
    assert b"NaN" not in payload and b"Infinity" not in payload


def test_error_bodies_keep_code_and_reason_and_clip_long_reasons() -> None:
    body = error_body(CommandError("rejected", "x" * 5000, limit="cable_length"))
    assert body["code"] == "rejected" and body["limit"] == "cable_length"
    assert len(body["reason"]) <= 600 and body["reason"].endswith("(clipped)")


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=20,
)


@given(data=json_values)
def test_any_json_gives_a_trajectory_or_a_clear_command_error(data: object) -> None:
    """Never another exception, whatever the JSON: the interface relies on it."""
    for candidate in (data, {"waypoints": data}, {"waypoints": [waypoint(0.0), data]}):
        try:
            decode_trajectory(candidate, LIMITS)
        except CommandError as exc:
            assert exc.code in ("bad_request", "rejected") and exc.reason


@given(name=st.sampled_from([*COMMANDS, "fly"]), data=json_values)
def test_any_json_gives_command_args_or_a_clear_command_error(name: str, data: object) -> None:
    for candidate in (data, {"position": data}):
        try:
            decode_command(name, candidate)
        except CommandError as exc:
            assert exc.code in ("bad_request", "rejected", "unknown_command") and exc.reason
