"""The zenoh interface's JSON messages: strict decoding, clear errors, versioned encoding."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr import Pose
from cdpr.trajectory import SCHEMA_VERSION, TrajectoryLimits
from daemon.interface import messages
from daemon.interface.messages import (
    ONE_PIECE_JSON_BYTES,
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


def standard_outcome(payload: bytes) -> object:
    """What the standard library's decoder alone makes of a payload (decode_json before
    orjson): the value, or the refusal's code and reason."""
    try:
        return messages._DECODER.decode(payload.decode("utf-8"))
    except RecursionError:
        return "bad_request", "JSON nested too deeply"
    except UnicodeDecodeError as exc:
        return "bad_request", f"payload is not UTF-8 text: {exc.reason}"
    except ValueError as exc:
        return "bad_request", f"invalid JSON: {exc}"


def fast_outcome(payload: bytes) -> object:
    try:
        return decode_json(payload, 1 << 20)
    except CommandError as exc:
        return exc.code, exc.reason


def same_json(a: object, b: object) -> bool:
    """Equal values of equal types all the way down (1 == 1.0 == True would hide a
    change); iterative, for deeply nested values."""
    pairs = [(a, b)]
    while pairs:
        x, y = pairs.pop()
        if type(x) is not type(y):
            return False
        if isinstance(x, dict):
            if list(x) != list(y):  # type: ignore[arg-type]
                return False
            pairs += [(x[k], y[k]) for k in x]  # type: ignore[index]
        elif isinstance(x, list | tuple):
            if len(x) != len(y):  # type: ignore[arg-type]
                return False
            pairs += zip(x, y, strict=True)  # type: ignore[arg-type]
        elif not (x == y or (x != x and y != y)):
            return False
    return True


JSON_TEXT = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=5)
    ),
    max_leaves=20,
).map(json.dumps)
SPLICES = st.sampled_from(
    ["", ",", "]", "}", '"', "NaN", "Infinity", "-Infinity", "1e400", "-1e999",
     "12345678901234567890123", "-9223372036854775809", '"\\ud800"', '"\\udc00x"',
     "\ufeff", "\x01", "0123", "[1,]", "tru", "\\", "\u00e9", " ", "\n"]
)  # fmt: skip


@given(JSON_TEXT, st.integers(min_value=0), SPLICES, st.booleans())
def test_the_fast_decoder_decides_as_the_standard_one(
    text: str, at: int, splice: str, replace: bool
) -> None:
    """Same value (types included) or the same refusal, for valid JSON and for copies
    with a token spliced in: big integers, lone surrogates, NaN, broken syntax, ..."""
    k = at % (len(text) + 1)
    for candidate in (text, text[:k] + splice + text[k + int(replace) :]):
        payload = candidate.encode("utf-8", "surrogatepass")
        assert same_json(fast_outcome(payload), standard_outcome(payload)), candidate


@pytest.mark.parametrize(
    "payload",
    [b"[" + b"12345678901234567890123" + b"]", b'{"a": -9223372036854775809}'],
)
def test_integers_beyond_64_bits_stay_exact(payload: bytes) -> None:
    """orjson would read them as floats; decode_json gives json.loads's exact int."""
    assert same_json(decode_json(payload, 1024), json.loads(payload))


def nested(depth: int, inner: str = "1") -> str:
    return "[" * depth + inner + "]" * depth


def on_a_fresh_stack(decide: Callable[[bytes], object], payload: bytes) -> object:
    """decide(payload) in a thread of its own, as a zenoh callback decodes: the json
    module's nesting limit counts the frames below it, and a test's stack is deeper under
    an xdist worker than in a plain run (950 deep then fell on either side of the limit,
    depending on the one frame decode_json adds)."""
    with ThreadPoolExecutor(1) as thread:
        return thread.submit(decide, payload).result()


@pytest.mark.parametrize(
    "text",
    [
        nested(899),
        nested(900),
        nested(20_000),
        json.dumps({"a": "[" * 5000, "b": [[1]] * 400}),  # brackets in strings do not nest
        # json.dumps({"a": "]" * 5000, "b": <950 nested lists>}), written out: built by
        # recursion it overflows the stack of an xdist worker at collection
        '{"a": "' + "]" * 5000 + '", "b": ' + nested(950) + "}",
        json.dumps({"a": '\\"[' * 1000, "b": "x\\", "c": [[[1]]]}),  # escapes in strings
        json.dumps({"a": "\\" * 3 + '"' + "{" * 1000}),
    ],
    ids=["899", "900", "20000", "in-strings", "after-closers", "escaped-quotes", "backslashes"],
)
def test_deep_nesting_is_decided_as_the_json_module_decides(text: str) -> None:
    """orjson nests without limit; from FAST_JSON_DEPTH on the json module decides
    (refusing nesting near Python's recursion limit), brackets in strings aside."""
    payload = text.encode()
    fast = on_a_fresh_stack(fast_outcome, payload)
    assert same_json(fast, on_a_fresh_stack(standard_outcome, payload))


def test_small_payloads_go_to_orjson(monkeypatch: pytest.MonkeyPatch) -> None:
    """Up to ONE_PIECE_JSON_BYTES a valid payload is one orjson call, never the standard
    decoder; above that the standard decoder works piece by piece."""
    calls: list[int] = []
    real = messages.orjson.loads
    monkeypatch.setattr(messages.orjson, "loads", lambda b: calls.append(len(b)) or real(b))
    body = {"id": "x", "waypoints": [waypoint(0.1 * k) for k in range(200)]}
    payload = json.dumps(body).encode()
    assert 16 * 1024 < len(payload) <= ONE_PIECE_JSON_BYTES
    assert decode_json(payload, 1 << 20) == body and calls == [len(payload)]
    large = json.dumps({"waypoints": [waypoint(0.1 * k) for k in range(500)]}).encode()
    assert len(large) > ONE_PIECE_JSON_BYTES
    assert decode_json(large, 1 << 22) == json.loads(large) and calls == [len(payload)]


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
