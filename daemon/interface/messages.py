"""JSON messages of the zenoh interface: schemas, strict decoding, encoding (DESIGN §10).

Every message carries {"version": 1} (the same key and number as the trajectory form of
cdpr.trajectory; optional on input, always present on output).  Quaternions are objects
{"w", "x", "y", "z"}; vectors are [x, y, z] lists (also {"x", "y", "z"} on input).

Inputs (objects; unknown keys, wrong types, NaN/Infinity tokens are refused):

    <prefix>/trajectory   put, or get with the body as the query payload
        {"version": 1, "id": "plan-42", "start": "now",     # or a unix time (s)
         "waypoints": [{"t": 0.0, "position": [..], "quaternion": {..}}, ...]}
        "id" (optional, 1..128 characters) is echoed in the reply and the events;
        "client", "preempt" (optional): as the commands' below;
        "start": when the first waypoint is due ("now", the default: at once);
        "waypoints": as documented in cdpr/trajectory/parse.py.
    <prefix>/cmd/<name>   get; payload optional (none, {} or {"version": 1}); any may name
        its "client" (1..128 printable characters, e.g. "alice@bench:4242": recorded
        in the events; "anonymous" without), and a command that moves the robot (goto,
        identify_payload, home, pretension) may say "preempt": true, to replace another
        client's motion (daemon.service.motion); and
        goto:  {"position": [x, y, z], "quaternion": {"w", "x", "y", "z"}}
               (quaternion optional: identity)
        brake: {"reason": "operator stop"}  (optional)
        payload: {"frozen": true} and/or {"mass": 11.0, "center_of_mass": [x, y, z]}
               (the payload estimate: freeze/unfreeze it, or set it; {} reports it);
               with {"frozen": true, "lease": 5.0} the freeze lapses unless renewed
               (the same again with the reply's "lease_id") within the lease (s); a
               release ({"frozen": false}) of a lease needs its "lease_id" too:
               daemon.service.lease
        identify_payload: {"apply": false}  (hold a few poses, estimate the payload
               statically, apply it if asked)
        home:  {"pose": "dock"}  (optional: a pose named in the robot file, default home)
        pretension: {"pose": "dock"}  (as home: the fixture's pose the platform rests at)
        observer: {"held": true}  (the external wrench observer out of the loop, or back
               in with false; {} reports it); "lease" as payload's

Outputs:

    reply   {"version": 1, "ok": true, "command": "enable", "result": {..handler body..}}
            {"version": 1, "ok": false, "command": "goto",
             "error": {"code": "bad_request", "reason": "...", "field": "position", ..}}
            (trajectory replies also carry "id"; errors are sent with Query.reply_err)
    event   {"version": 1, "seq": 7, "time": 1718000000.25, "event": "trajectory_rejected",
             "id": "plan-42", "error": {..}}      (see EVENT_KEY)
    state   {"version": 1, "seq": 1234, "time": 1718000000.02, **handler.state(),
             "interface": {counters of received, refused and dropped messages}}

"time" is the sender's unix time (s).  Non-finite numbers are sent as null.
"""

from __future__ import annotations

import contextlib
import enum
import json
import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson

from cdpr.path import Path, parse_path
from cdpr.pose import QUATERNION_NORM_TOLERANCE, Pose
from cdpr.trajectory import (
    SCHEMA_VERSION,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    parse_trajectory,
)
from daemon.service.api import (
    ANONYMOUS,
    COMMANDS,
    UNNAMED,
    Claim,
    CommandError,
    trajectory_error_details,
)

VERSION_KEY = "version"
MAX_ID_CHARS = 128
MAX_REASON_CHARS = 600  # error texts echo input (e.g. unknown keys): keep replies small
EVENT_KEY = "event"  # the name of an event: trajectory_accepted / _rejected (interface),
# state, fault, ... (service)
MAX_BRAKE_REASON = 200
MAX_POSE_NAME = 64  # the robot file's pose names
MAX_CLIENT_CHARS = 128  # a client's name
MAX_LEASE_ID_CHARS = 64  # the daemon's lease ids are 24 hex digits
LEASE_MAX = 60.0  # s: the longest lease on a payload freeze or an observer hold
_ARGS = {
    "goto": ("position", "quaternion", "preempt"),
    "brake": ("reason",),
    "payload": ("frozen", "mass", "center_of_mass", "lease", "lease_id"),
    "identify_payload": ("apply", "preempt"),
    "home": ("pose", "preempt"),
    "pretension": ("pose", "preempt"),
    "observer": ("held", "lease", "lease_id"),
}
_IDENTITY = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")
ONE_PIECE_JSON_BYTES = 32 * 1024
"""Payloads up to this size are decoded by one call of a C decoder (orjson: ~4 µs per
KiB, the standard library's: ~15 µs, <= ~0.5 ms); longer ones piece by piece (see
decode_json), so that no call holds the GIL for long."""
JSON_PIECE = 16 * 1024  # characters: the most the C decoder reads at once in a long payload
MAX_JSON_DEPTH = 1000  # nesting, as deep as the C decoder goes
FAST_JSON_DEPTH = 900  # nesting from which the json module decides (orjson has no limit)
_WINDOWS = (512, JSON_PIECE)  # try a short piece first: most values are small
_WHITESPACE = re.compile(r"[ \t\n\r]*")


@dataclass(frozen=True)
class TrajectoryRequest:
    """A decoded trajectory message: the sender's id, the start time, the trajectory,
    and who sends it (its claim: client, preempt, id)."""

    id: str | None
    start: float | None  # unix time (s), None: as soon as possible
    trajectory: Trajectory
    claim: Claim = UNNAMED


@dataclass(frozen=True)
class TrajectoryMessage:
    """A trajectory or path message whose head is checked (check_trajectory_head): the
    sender's id, the start time, the body still to parse, how many waypoints (a path:
    poses) it lists, who sends it, and whether it is a path (poses to be timed)."""

    id: str | None
    start: float | None
    body: dict[str, Any]
    waypoints: int
    claim: Claim = UNNAMED
    path: bool = False


def no_checkpoint() -> None:
    """decode_json's default checkpoint: nothing to pause for."""


def decode_json(
    payload: bytes, max_bytes: int, checkpoint: Callable[[], None] = no_checkpoint
) -> Any:
    """Strict JSON: size-limited, UTF-8, no NaN/Infinity tokens, nesting within Python's
    recursion limit.

    A payload of at most ONE_PIECE_JSON_BYTES is decoded by orjson (4-5x faster than
    the standard library) unless it holds an integer of 19 digits or more, which orjson
    would turn into a float, or nests FAST_JSON_DEPTH deep, which orjson would allow.
    What orjson refuses, and every longer payload, goes to the standard library's
    decoder, which names the problem (and accepts what orjson alone refuses, such as a
    lone surrogate escape), so the result is always json.loads's.
    A C decoder holds the GIL for a whole call, so a payload above ONE_PIECE_JSON_BYTES
    is decoded piece by piece: containers are walked here, each value of at most
    JSON_PIECE characters goes to the standard library's C decoder at once, and a string
    or number longer than that is refused; `checkpoint` is called before each value (the
    parse thread pauses there: daemon.interface.zenoh_io).
    """
    check_size(len(payload), max_bytes)
    if len(payload) <= ONE_PIECE_JSON_BYTES and not (_long_integer(payload) or _deep(payload)):
        with contextlib.suppress(orjson.JSONDecodeError, RecursionError):
            return orjson.loads(payload)
    try:
        text = payload.decode("utf-8")
        if len(payload) <= ONE_PIECE_JSON_BYTES:
            return _DECODER.decode(text)
        return _decode_in_pieces(text, checkpoint)
    except RecursionError:
        raise CommandError("bad_request", "JSON nested too deeply") from None
    except UnicodeDecodeError as exc:
        raise CommandError("bad_request", f"payload is not UTF-8 text: {exc.reason}") from None
    except ValueError as exc:  # json.JSONDecodeError or a refused constant
        raise CommandError("bad_request", f"invalid JSON: {exc}") from None


def _decode_in_pieces(text: str, checkpoint: Callable[[], None] = no_checkpoint) -> Any:
    """json.loads(text), handing the C decoder at most JSON_PIECE characters at a time,
    calling `checkpoint` before each."""
    size = len(text)
    stack: list[list[Any]] = []  # [container, the key of the value being read (objects)]
    pos = _skip_space(text, 0)
    while True:
        checkpoint()
        value, end = _value_in_piece(text, pos)
        if end >= 0:
            pos = end
        else:  # a container longer than a piece: walk it
            if len(stack) >= MAX_JSON_DEPTH:
                raise RecursionError
            value = [] if text[pos] == "[" else {}
            pos = _skip_space(text, pos + 1)
            if text.startswith("]" if isinstance(value, list) else "}", pos):
                pos += 1
            else:
                stack.append([value, None])
                if isinstance(value, dict):
                    pos = _member_key(text, pos, stack[-1])
                continue
        while True:  # put the value in its container; close finished containers
            if not stack:
                pos = _skip_space(text, pos)
                if pos != size:
                    raise json.JSONDecodeError("Extra data", text, pos)
                return value
            frame = stack[-1]
            container = frame[0]
            if isinstance(container, list):
                container.append(value)
            else:
                container[frame[1]] = value
            pos = _skip_space(text, pos)
            char = text[pos : pos + 1]
            if char == ",":
                pos = _skip_space(text, pos + 1)
                if isinstance(container, dict):
                    pos = _member_key(text, pos, frame)
                break
            if char != ("]" if isinstance(container, list) else "}"):
                raise json.JSONDecodeError("Expecting ',' delimiter", text, pos)
            stack.pop()
            value, pos = container, pos + 1


def _value_in_piece(text: str, pos: int) -> tuple[Any, int]:
    """(the value at pos, where it ends), or (None, -1) for a container longer than a
    piece; JSONDecodeError for bad JSON and for strings and numbers that long."""
    for window in _WINDOWS:
        piece = text[pos : pos + window]
        try:
            value, end = _DECODER.raw_decode(piece)
        except json.JSONDecodeError as exc:
            error = exc
            continue
        if end < len(piece) or pos + end >= len(text):  # a number cut at the piece's end
            return value, pos + end  # is not whole
        error = None
    if pos + len(piece) < len(text):  # the value goes on beyond the piece
        if text[pos] in "[{":
            return None, -1
        if error is None or error.pos >= len(piece) or error.msg.startswith("Unterminated"):
            raise json.JSONDecodeError(
                f"a string or number longer than {JSON_PIECE} characters", text, pos
            )
    assert error is not None
    raise json.JSONDecodeError(error.msg, text, pos + error.pos)


def _member_key(text: str, pos: int, frame: list[Any]) -> int:
    """Read '"key" :' at pos into frame[1]; the position of the member's value."""
    if text[pos : pos + 1] != '"':
        raise json.JSONDecodeError("Expecting property name enclosed in double quotes", text, pos)
    piece = text[pos + 1 : pos + 1 + JSON_PIECE]
    try:
        frame[1], end = json.decoder.scanstring(piece, 0, True)
    except json.JSONDecodeError as exc:
        if pos + 1 + len(piece) < len(text) and exc.msg.startswith("Unterminated"):
            message = f"a string longer than {JSON_PIECE} characters"
            raise json.JSONDecodeError(message, text, pos) from None
        raise json.JSONDecodeError(exc.msg, text, pos + 1 + exc.pos) from None
    pos = _skip_space(text, pos + 1 + end)
    if text[pos : pos + 1] != ":":
        raise json.JSONDecodeError("Expecting ':' delimiter", text, pos)
    return _skip_space(text, pos + 1)


def _skip_space(text: str, pos: int) -> int:
    while True:
        end = _WHITESPACE.match(text, pos, pos + JSON_PIECE).end()
        if end < pos + JSON_PIECE:
            return end
        pos = end


def check_size(size: int, max_bytes: int, limit: str = "max_message_bytes") -> None:
    """Refuse a message above `max_bytes` (the `limit` named in the error) unread."""
    if size > max_bytes:
        raise CommandError(
            "bad_request",
            f"message of {size} bytes exceeds the limit of {max_bytes} bytes",
            limit=limit,
            value=size,
        )


def request_id(data: Any) -> str | None:
    """The sender's id if there is a valid one (also for messages rejected otherwise)."""
    if isinstance(data, dict):
        value = data.get("id")
        if isinstance(value, str) and 0 < len(value) <= MAX_ID_CHARS:
            return value
    return None


def decode_trajectory(data: Any, limits: TrajectoryLimits) -> TrajectoryRequest:
    """A trajectory message -> TrajectoryRequest; CommandError names the problem.

    Schema problems give code "bad_request"; a well-formed trajectory that breaks a rule
    of its own (times not increasing, a non-unit quaternion, ...) gives "rejected".
    Either way the error carries the failing limit, waypoint and field.  The same as
    parse_waypoints(check_trajectory_head(data, limits), limits).
    """
    return parse_waypoints(check_trajectory_head(data, limits), limits)


def check_trajectory_head(
    data: Any, limits: TrajectoryLimits, path: bool = False
) -> TrajectoryMessage:
    """The cheap part of decode_trajectory (O(1) and a count): everything but the
    waypoints themselves, which parse_waypoints reads (~0.07 ms a waypoint); with `path`,
    the same envelope around a path's poses (time_path_message)."""
    what = "path" if path else "trajectory"
    _check_object(data, what)
    body = dict(data)
    _check_version(body.pop(VERSION_KEY, SCHEMA_VERSION))
    ident = body.pop("id", None)
    if ident is not None and request_id({"id": ident}) is None:
        raise CommandError(
            "bad_request", f"id: expected a string of 1..{MAX_ID_CHARS} characters", field="id"
        )
    start = _start_time(body.pop("start", "now"))
    claim = Claim(
        _client(body.pop("client", ANONYMOUS)),
        _flag({"preempt": body.pop("preempt", False)}, "preempt", what),
        ident,
    )
    key = "poses" if path else "waypoints"
    listed = body.get(key)
    if isinstance(listed, list) and len(listed) > limits.max_waypoints:
        raise CommandError(
            "rejected",
            f"{len(listed)} {key} exceed the limit of {limits.max_waypoints}",
            limit="max_waypoints",
            value=len(listed),
            field=key,
        )
    count = len(listed) if isinstance(listed, list) else 0
    return TrajectoryMessage(ident, start, body, count, claim, path)


def parse_waypoints(message: TrajectoryMessage, limits: TrajectoryLimits) -> TrajectoryRequest:
    """The rest of decode_trajectory: the waypoints, and the C² curve through them."""
    with _refused_as_command_error():
        trajectory = parse_trajectory(message.body, limits)
    return TrajectoryRequest(message.id, message.start, trajectory, message.claim)


def time_path_message(
    message: TrajectoryMessage,
    limits: TrajectoryLimits,
    timer: Callable[[Path], Trajectory],
) -> TrajectoryRequest:
    """A path message's poses (cdpr.path.parse_path), timed by `timer` (the daemon's:
    cdpr.path.timing within the robot's tensions) into the trajectory to run."""
    with _refused_as_command_error():
        trajectory = timer(parse_path(message.body, limits))
    return TrajectoryRequest(message.id, message.start, trajectory, message.claim)


@contextlib.contextmanager
def _refused_as_command_error() -> Iterator[None]:
    """A TrajectoryError as the CommandError a sender gets: bad_request for the schema,
    rejected for a limit (with its details)."""
    try:
        yield
    except TrajectoryError as exc:
        code = "bad_request" if exc.limit == "schema" else "rejected"
        raise CommandError(code, clip(str(exc)), **trajectory_error_details(exc)) from None


def decode_command(
    name: str, data: Any, unit_tolerance: float = QUATERNION_NORM_TOLERANCE
) -> dict[str, Any]:
    """Command `name` with body `data` -> the handler's args.  The body is a JSON object
    (an empty payload stands for {}); null, an array, a number or a string is refused,
    since a command must never run on a body that is not what its sender meant."""
    if name not in COMMANDS:
        raise CommandError(
            "unknown_command",
            clip(f"unknown command {name!r} (commands: {', '.join(COMMANDS)})"),
            field="command",
        )
    _check_object(data, name)
    _no_unknown_keys(data, (VERSION_KEY, "client", *_ARGS.get(name, ())), name)
    _check_version(data.get(VERSION_KEY, SCHEMA_VERSION))
    claim: dict[str, Any] = {}
    if "client" in data:
        claim["client"] = _client(data["client"])
    if _flag(data, "preempt", name):
        claim["preempt"] = True
    return {**_command_args(name, data, unit_tolerance), **claim}


def _command_args(name: str, data: dict[str, Any], unit_tolerance: float) -> dict[str, Any]:
    """decode_command's args of command `name` itself (its client's are added there)."""
    if name == "brake":
        reason = data.get("reason")
        if reason is None:
            return {}
        if not isinstance(reason, str) or len(reason) > MAX_BRAKE_REASON:
            raise CommandError(
                "bad_request",
                f"brake.reason: expected a string of up to {MAX_BRAKE_REASON} characters",
                field="reason",
            )
        return {"reason": reason}
    if name == "payload":
        return _payload_args(data)
    if name == "identify_payload":
        return {"apply": True} if _flag(data, "apply", "identify_payload") else {}
    if name == "observer":
        args = {"held": _flag(data, "held", "observer")} if "held" in data else {}
        return _leased(data, args, "held", "observer")
    if name in ("home", "pretension"):
        pose = data.get("pose")
        if pose is None:
            return {}
        if not isinstance(pose, str) or not 0 < len(pose) <= MAX_POSE_NAME:
            raise CommandError(
                "bad_request",
                f"{name}.pose: expected a pose name of up to {MAX_POSE_NAME} characters",
                field="pose",
            )
        return {"pose_name": pose}
    if name != "goto":
        return {}
    if "position" not in data:
        raise CommandError("bad_request", "goto: missing key 'position'", field="position")
    position = _vec3(data["position"], "position")
    quaternion = _unit_quaternion(data.get("quaternion", _IDENTITY), "quaternion", unit_tolerance)
    return {"pose": Pose(position, quaternion)}


def _payload_args(data: dict[str, Any]) -> dict[str, Any]:
    """payload: {"frozen"} and/or {"mass", "center_of_mass"} (both or neither)."""
    args: dict[str, Any] = {}
    if "frozen" in data:
        args["frozen"] = _flag(data, "frozen", "payload")
    if ("mass" in data) != ("center_of_mass" in data):
        missing = "center_of_mass" if "mass" in data else "mass"
        raise CommandError(
            "bad_request", f"payload: give mass and center_of_mass together ({missing} missing)",
            field=missing,
        )  # fmt: skip
    if "mass" in data:
        mass = data["mass"]
        if type(mass) not in (int, float) or not (math.isfinite(mass) and mass > 0.0):
            raise CommandError(
                "bad_request", "payload.mass: expected a positive number (kg)", field="mass"
            )
        args["mass"] = float(mass)
        args["center_of_mass"] = _vec3(data["center_of_mass"], "center_of_mass")
    return _leased(data, args, "frozen", "payload")


def _client(name: Any) -> str:
    """A client's name: 1..MAX_CLIENT_CHARS printable characters."""
    if not (isinstance(name, str) and 0 < len(name) <= MAX_CLIENT_CHARS and name.isprintable()):
        raise CommandError(
            "bad_request",
            f"client: expected a name of 1..{MAX_CLIENT_CHARS} printable characters",
            field="client",
        )
    return name


def _leased(data: dict[str, Any], args: dict[str, Any], key: str, where: str) -> dict[str, Any]:
    """`args` with data's "lease_id" (only with `key`: a renewal or a release) and "lease"
    (s) if it has them: the lease only with `key` true (what it lapses), a finite number
    of seconds above 0 and at most LEASE_MAX."""
    if "lease_id" in data:
        ident = data["lease_id"]
        if key not in data:
            problem = f"only with {key} (to renew or release the lease)"
            raise CommandError("bad_request", f"{where}.lease_id: {problem}", field="lease_id")
        if not (isinstance(ident, str) and 0 < len(ident) <= MAX_LEASE_ID_CHARS):
            problem = f"expected the lease's id, a string of 1..{MAX_LEASE_ID_CHARS} characters"
            raise CommandError("bad_request", f"{where}.lease_id: {problem}", field="lease_id")
        args = {**args, "lease_id": ident}
    if "lease" not in data:
        return args
    lease = data["lease"]
    if not args.get(key):
        problem = f"only with {key}: true (the lease ends that)"
    elif type(lease) not in (int, float) or not math.isfinite(lease):
        problem = "expected a number of seconds"
    elif lease <= 0.0:
        problem = f"{lease!r} s: must be more than 0"
    elif lease > LEASE_MAX:
        problem = f"{lease!r} s: at most {LEASE_MAX:g}"
    else:
        return {**args, "lease": float(lease)}
    raise CommandError("bad_request", f"{where}.lease: {problem}", field="lease")


def _flag(data: dict[str, Any], key: str, where: str) -> bool:
    value = data.get(key, False)
    if not isinstance(value, bool):
        raise CommandError("bad_request", f"{where}.{key}: expected true or false", field=key)
    return value


def reply_ok(command: str, result: dict[str, Any], ident: str | None = None) -> dict[str, Any]:
    head = _with_id({VERSION_KEY: SCHEMA_VERSION, "ok": True, "command": command}, ident)
    return {**head, "result": result}


def reply_error(command: str, error: CommandError, ident: str | None = None) -> dict[str, Any]:
    head = _with_id({VERSION_KEY: SCHEMA_VERSION, "ok": False, "command": command}, ident)
    return {**head, "error": error_body(error)}


def error_body(error: CommandError) -> dict[str, Any]:
    """{"code", "reason", then the details (limit, waypoint, field, value, ...)}."""
    return {"code": error.code, "reason": clip(error.reason), **error.details}


def encode(message: dict[str, Any]) -> bytes:
    """Compact strict JSON; numpy values become plain numbers, non-finite ones null."""
    return json.dumps(jsonable(message), separators=(",", ":"), allow_nan=False).encode()


def jsonable(value: Any) -> Any:
    """A JSON-safe copy: numpy -> Python, tuples -> lists, NaN/inf -> None, other -> str."""
    if value is None or isinstance(value, bool | str | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, enum.Enum):
        return value.name
    return clip(str(value), 200)


def clip(text: str, limit: int = MAX_REASON_CHARS) -> str:
    return text if len(text) <= limit else text[: limit - 15] + " ... (clipped)"


def _with_id(message: dict[str, Any], ident: str | None) -> dict[str, Any]:
    return message if ident is None else {**message, "id": ident}


def _refuse_constant(token: str) -> Any:
    raise ValueError(f"{token} is not a JSON number (non-finite values are refused)")


_DECODER = json.JSONDecoder(parse_constant=_refuse_constant)

# bytes.translate table: digits -> "0", what may stand before an integer token -> " ",
# anything else -> "x" (so a fraction's digits, after ".", never look like an integer)
_INTEGER_CLASSES = bytes(
    ord("0") if chr(c) in "0123456789" else ord(" ") if chr(c) in "-,:[ \t\n\r" else ord("x")
    for c in range(256)
)
_LONG_INTEGER = b" " + b"0" * 19
_NOT_NESTING = bytes(c for c in range(256) if chr(c) not in '[]{}"')  # _deep drops these


def _long_integer(payload: bytes) -> bool:
    """payload may hold an integer token of 19 or more digits (orjson reads one beyond
    64 bits as a float, json.loads as an exact int); a digit run in a string may make
    this true too (then the standard decoder does the work, to the same result)."""
    return _LONG_INTEGER in (b" " + payload).translate(_INTEGER_CLASSES)


def _deep(payload: bytes) -> bool:
    """payload nests arrays and objects FAST_JSON_DEPTH deep or more, outside strings (for
    valid JSON; the json module refuses nesting near Python's recursion limit, orjson
    does not).  Escapes are dropped first (an escaped backslash, then an escaped quote),
    then all but brackets and quotes: what is left is short, and its quotes are real."""
    if payload.count(b"[") + payload.count(b"{") < FAST_JSON_DEPTH:
        return False
    left = payload.replace(b"\\\\", b"").replace(b'\\"', b"").translate(None, _NOT_NESTING)
    b = np.frombuffer(left, dtype=np.uint8)
    in_string = np.cumsum(b == ord('"')) % 2 == 1  # an opening quote counts as inside
    step = (b == ord("[")).astype(np.int64) + (b == ord("{")) - (b == ord("]")) - (b == ord("}"))
    step[in_string] = 0
    return bool(np.cumsum(step).max() >= FAST_JSON_DEPTH)


def _check_object(data: Any, what: str) -> None:
    if not isinstance(data, dict):
        raise CommandError("bad_request", f"{what}: expected a JSON object, got {_kind(data)}")


def _check_version(version: Any) -> None:
    if type(version) is not int or version != SCHEMA_VERSION:
        raise CommandError(
            "bad_request",
            clip(f"version: unsupported schema version {version!r} (this daemon speaks 1)"),
            field=VERSION_KEY,
        )


def _no_unknown_keys(body: dict[str, Any], allowed: tuple[str, ...], where: str) -> None:
    unknown = sorted(repr(k) for k in body if k not in allowed)
    if unknown:
        raise CommandError(
            "bad_request",
            clip(f"{where}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(allowed)})"),
            field=where,
        )


def _start_time(value: Any) -> float | None:
    if value == "now":
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CommandError(
            "bad_request",
            f'start: expected "now" or a unix time in seconds, got {_kind(value)}',
            field="start",
        )
    start = float(value) if abs(value) < 1e300 else math.inf
    if not (math.isfinite(start) and start > 0.0):
        raise CommandError(
            "bad_request", f"start: {start!r} is not a unix time in seconds", field="start"
        )
    return start


def _number(x: Any, where: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise CommandError(
            "bad_request", f"{where}: expected a number, got {_kind(x)}", field=where
        )
    value = float(x) if abs(x) < 1e300 else math.inf
    if not math.isfinite(value):
        raise CommandError("bad_request", f"{where}: not a finite number", field=where)
    return value


def _vec3(x: Any, where: str) -> tuple[float, ...]:
    if isinstance(x, dict):
        _no_unknown_keys(x, _XYZ, where)
        if set(x) != set(_XYZ):
            raise CommandError("bad_request", f"{where}: needs x, y and z", field=where)
        return tuple(_number(x[k], f"{where}.{k}") for k in _XYZ)
    if not isinstance(x, list) or len(x) != 3:
        raise CommandError(
            "bad_request",
            f"{where}: expected [x, y, z] or {{x, y, z}}, got {_kind(x)}",
            field=where,
        )
    return tuple(_number(c, f"{where}[{k}]") for k, c in enumerate(x))


def _unit_quaternion(x: Any, where: str, tolerance: float) -> tuple[float, ...]:
    if not isinstance(x, dict):
        raise CommandError(
            "bad_request",
            f"{where}: a quaternion is an object {{w, x, y, z}}, got {_kind(x)}",
            field=where,
        )
    _no_unknown_keys(x, _WXYZ, where)
    if set(x) != set(_WXYZ):
        raise CommandError("bad_request", f"{where}: needs w, x, y and z", field=where)
    w, qx, qy, qz = (_number(x[k], f"{where}.{k}") for k in _WXYZ)
    norm = math.sqrt(w * w + qx * qx + qy * qy + qz * qz)
    if not abs(norm - 1.0) <= tolerance:
        raise CommandError(
            "rejected",
            f"{where} has norm {norm:.9g}; a unit quaternion (within {tolerance:g}) is required",
            field=where,
            limit="unit_quaternion",
            value=norm,
        )
    return (w / norm, qx / norm, qy / norm, qz / norm)


def _kind(x: Any) -> str:
    return "null" if x is None else type(x).__name__
