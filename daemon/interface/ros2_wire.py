"""rmw_zenoh's wire format, so that ROS 2 nodes on rmw_zenoh_cpp see cdprd as a node
(DESIGN §17; docs/guide/ros2.md).  No ROS install: CDR and RIHS01 type hashes come from
`rosbags` (message definitions shipped in the package, ROS 2 Jazzy store).

Followed exactly: rmw_zenoh_cpp as released for Jazzy from 0.2.4 on (and Rolling from
0.6.0, Humble from 0.1.2), i.e. after ros2/rmw_zenoh#601 made the attachment positional.
The sources read (tests/data/rmw_zenoh_reference.md keeps the excerpts):
docs/design.md @ 99a6a2bd10b949052f4f12c5854825dc005e95a5,
rmw_zenoh_cpp/src/detail/liveliness_utils.cpp @ 3411fdec149fe0c932f24d4d79ef908eb81d7482,
rmw_zenoh_cpp/src/detail/attachment_helpers.cpp @ 534747dca92adf15e1b1b975123037ca278db5ba,
rmw_zenoh_cpp/src/detail/rmw_publisher_data.cpp @ 3e19ec730c529035a648aec80c0ae0a056943b8c,
rmw_zenoh_cpp/src/detail/qos.cpp @ 5e10d47b06c3fe327105d06a8350be455411ea5b.

- Data key: <domain_id>/<fully qualified topic without its leading "/">/<DDS type
  name>/<RIHS01 type hash>, e.g. 0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...
- Payload: the message in CDR with its 4-byte encapsulation header (little endian).
- Attachment: sequence number (int64 LE, from 1 per publisher), source timestamp (int64
  LE, ns since the UNIX epoch), the publisher's GID as zenoh-ext serializes a 16-byte
  array (one LEB128 length byte, 16, then the bytes): 33 bytes.  A sample without one
  is dropped by rmw_zenoh ("Unable to obtain attachment"), so it is refused here too.
- Liveliness tokens: @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>[/<topic>/<type>/<hash>/<qos>], each name with "/" mangled to
  "%"; kind NN (node, whose entity id is its node id), MP, MS; qos in rmw_zenoh's
  compact form, empty fields for its defaults (qos_keyexpr).
- A TRANSIENT_LOCAL publisher (rmw_publisher_data.cpp @ 3e19ec73..., Jazzy from 0.2.4)
  is a zenoh-ext AdvancedPublisher with publisher_detection, a cache of `depth` samples
  and, being reliable, sample miss detection with a sporadic heartbeat of 500 ms; a
  late-joining transient-local subscription (an AdvancedSubscriber whose history detects
  late publishers) queries that cache.
- GID: XXH3-128 of the entity's liveliness key, low 64 bits then high 64 bits, each in
  the host's (little-endian) byte order.
- Service servers (rmw_zenoh_cpp/src/detail/rmw_service_data.cpp): a queryable (complete)
  on the key above with the service's type (std_srvs::srv::dds_::Trigger_, SetBool_) and the
  service type's hash, and a liveliness token of kind SS.  A request is the Request in
  CDR with the client's attachment (its sequence number, timestamp and GID); one whose
  CDR or attachment does not read is taken and never answered.  The reply, on the
  service's key, is the Response in CDR with the attachment (the request's sequence
  number, the server's time, the client's GID).
- A service type's RIHS01 hash (REP-2016) covers request_message, response_message and
  event_message (<srv>_Event: service_msgs/msg/ServiceEventInfo info, request and
  response as sequences of at most one).  rosbags has no std_srvs and writes
  ServiceEventInfo's client_gid as char[16], where rosidl (its .msg -> .idl maps char to
  uint8) writes uint8[16]: the hashes are computed here in a store of their own, and
  give Jazzy's (tests/data/rmw_zenoh_reference.md).
"""

from __future__ import annotations

import contextlib
import logging
import re
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import xxhash
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

log = logging.getLogger(__name__)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE_SERVER = "NN", "MP", "MS", "SS"
TRIGGER, SET_BOOL = "std_srvs/srv/Trigger", "std_srvs/srv/SetBool"
RMW_ZENOH_DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth (qos.cpp)
TRANSIENT_LOCAL = 1  # rmw_qos_durability_policy_e (rmw/types.h); VOLATILE (2) is the default
CANCEL_GOAL = "action_msgs/srv/CancelGoal"  # every action's cancel_goal service
TIME, UUID = "builtin_interfaces/msg/Time", "unique_identifier_msgs/msg/UUID"
GOAL_INFO = "action_msgs/msg/GoalInfo"
GID_SIZE = 16
_ATTACHMENT = struct.Struct("<qqB16s")


class WireError(ValueError):
    """A sample that is not in rmw_zenoh's format: the message names what is wrong."""


class Attachment(NamedTuple):
    sequence_number: int
    source_timestamp: int  # ns since the UNIX epoch
    source_gid: bytes


def _field(typ: str) -> tuple[Nodetype, tuple[str, int]]:
    return Nodetype.BASE, (typ, 0)


def _nested(typ: str, bound: int | None = None) -> Any:
    return (
        (Nodetype.NAME, typ)
        if bound is None
        else (Nodetype.SEQUENCE, ((Nodetype.NAME, typ), bound))
    )


def _service_types(srvtype: str, request: list[Any], response: list[Any]) -> dict[str, Any]:
    """rosbags' field definitions of a service's Request, Response, Event and the
    service type itself (the struct REP-2016 hashes).  An empty Request has rosidl's
    placeholder field, as on the wire."""
    req, res, event = (f"{srvtype}_{part}" for part in ("Request", "Response", "Event"))
    return {
        req: ([], _fields(request)),
        res: ([], _fields(response)),
        event: (
            [],
            [
                ("info", _nested(_EVENT_INFO)),
                ("request", _nested(req, 1)),
                ("response", _nested(res, 1)),
            ],
        ),
        srvtype: (
            [],
            [
                ("request_message", _nested(req)),
                ("response_message", _nested(res)),
                ("event_message", _nested(event)),
            ],
        ),
    }


def _fields(fields: list[Any]) -> list[Any]:
    """rosidl gives a struct without fields a placeholder uint8 (and so does the wire)."""
    return fields or [("structure_needs_at_least_one_member", _field("uint8"))]


def action_types(action: str, text: str) -> dict[str, Any]:
    """rosbags' field definitions of action `action` (pkg/action/Name) from its .action
    `text` (goal, result and feedback, each in .msg syntax, between lines "---"), and of
    what rosidl derives from it (rosidl_generator_c's action/detail/*__description.c):
    <Name>_Goal, _Result, _Feedback; the services _SendGoal (Request: goal_id, goal;
    Response: accepted, stamp) and _GetResult (Request: goal_id; Response: status,
    result), each with its Request, Response and Event; _FeedbackMessage (goal_id,
    feedback); and the action type itself, the struct REP-2016 hashes (goal, result,
    feedback, send_goal_service, get_result_service, feedback_message)."""
    parts = re.split(r"^---[ \t]*$", text, flags=re.MULTILINE)
    if len(parts) != 3:
        raise ValueError(f"{action}: {len(parts)} parts, an .action has goal---result---feedback")
    names = [f"{action}_{part}" for part in ("Goal", "Result", "Feedback")]
    out: dict[str, Any] = {}
    for name, part in zip(names, parts, strict=True):
        consts, fields = get_types_from_msg(part, name)[name]
        out[name] = (consts, _fields(fields))
    goal, result, feedback = names
    send_goal, get_result, message = (
        f"{action}_{part}" for part in ("SendGoal", "GetResult", "FeedbackMessage")
    )
    goal_id = ("goal_id", _nested(UUID))
    out.update(
        _service_types(
            send_goal,
            [goal_id, ("goal", _nested(goal))],
            [("accepted", _field("bool")), ("stamp", _nested(TIME))],
        )
    )
    out.update(
        _service_types(
            get_result, [goal_id], [("status", _field("int8")), ("result", _nested(result))]
        )
    )
    out[message] = ([], [goal_id, ("feedback", _nested(feedback))])
    out[action] = (
        [],
        [
            ("goal", _nested(goal)),
            ("result", _nested(result)),
            ("feedback", _nested(feedback)),
            ("send_goal_service", _nested(send_goal)),
            ("get_result_service", _nested(get_result)),
            ("feedback_message", _nested(message)),
        ],
    )
    return out


_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
_HASHES = get_typestore(Stores.EMPTY)  # the types as rosidl hashes them (see register)
_HASHED: set[str] = set()  # the types whose hash _HASHES gives
_CARRIED = ("_Request", "_Response", "_Goal", "_Result", "_Feedback", "_FeedbackMessage")


def register(types: dict[str, Any]) -> None:
    """Make derived types (_service_types, action_types) known: those a sample carries
    (no Event, no service or action struct) in TYPESTORE, for CDR; all of them, with the
    Jazzy types they refer to, in a store of their own for their hashes, where
    ServiceEventInfo's client_gid is uint8[16] as rosidl types it (rosbags: char[16])."""
    TYPESTORE.register({name: fields for name, fields in types.items() if name.endswith(_CARRIED)})
    needed: set[str] = set()
    todo = [ref for fields in types.values() for ref in _references(fields)]
    while todo:
        name = todo.pop()
        if name in types or name in needed or name in _HASHES.fielddefs:
            continue
        needed.add(name)
        todo += _references(TYPESTORE.fielddefs[name])
    known = {name: TYPESTORE.fielddefs[name] for name in needed}
    if _EVENT_INFO in known:
        consts, fields = known[_EVENT_INFO]
        known[_EVENT_INFO] = (
            consts,
            [
                (n, (Nodetype.ARRAY, (_field("uint8"), 16)) if n == "client_gid" else d)
                for n, d in fields
            ],
        )
    _HASHES.register(known)
    _HASHES.register(types)
    _HASHED.update(types)


def _references(definition: tuple[Any, list[Any]]) -> list[str]:
    """The type names the fields of a rosbags definition refer to."""
    out = []
    for _name, (kind, detail) in definition[1]:
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            kind, detail = detail[0]
        if kind == Nodetype.NAME:
            out.append(detail)
    return out


_ANSWER = [("success", _field("bool")), ("message", _field("string"))]  # std_srvs' Response
register(
    {
        **_service_types(TRIGGER, [], _ANSWER),
        **_service_types(SET_BOOL, [("data", _field("bool"))], _ANSWER),
        **_service_types(
            CANCEL_GOAL,
            [("goal_info", _nested(GOAL_INFO))],
            [
                ("return_code", _field("int8")),
                ("goals_canceling", (Nodetype.SEQUENCE, (_nested(GOAL_INFO), 0))),
            ],
        ),
    }
)


def qos_keyexpr(depth: int = 10, transient_local: bool = False) -> str:
    """rmw_zenoh's compact form (qos_to_keyexpr) of a reliable, keep-last `depth` QoS
    profile, volatile or transient-local: reliability:durability:history,depth:deadline:
    lifespan:liveliness,lease s,lease ns, each field empty where it is rmw_zenoh's default
    (reliable, volatile, keep last 42, infinite durations, automatic liveliness)."""
    durability = str(TRANSIENT_LOCAL) if transient_local else ""
    written = "" if depth == RMW_ZENOH_DEFAULT_DEPTH else str(depth)
    return f":{durability}:,{written}:,:,:,,"


# reliable, volatile, keep last 10: rclcpp's default profile, and the services' default
DEFAULT_QOS = qos_keyexpr(10)


def dds_type_name(msgtype: str) -> str:
    """geometry_msgs/msg/PoseStamped -> geometry_msgs::msg::dds_::PoseStamped_"""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(msgtype: str) -> str:
    """The RIHS01 type hash of message or service type `msgtype` (REP-2016), as rosbags
    computes it (a service's in the store above)."""
    store = _HASHES if msgtype in _HASHED else TYPESTORE
    return store.hash_rihs01(msgtype)


def topic_key(domain_id: int, topic: str, msgtype: str) -> str:
    """The zenoh key of fully qualified `topic` carrying `msgtype`."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"


def mangle(name: str) -> str:
    return name.replace("/", "%")


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as rmw_zenoh announces it: its session's zid and its id there."""

    domain_id: int
    zid: str
    node_id: int
    namespace: str
    name: str
    enclave: str = "/"

    def _head(self, entity_id: int, kind: str) -> str:
        return "/".join(
            (
                ADMIN_SPACE,
                str(self.domain_id),
                self.zid,
                str(self.node_id),
                str(entity_id),
                kind,
                mangle(self.enclave),
                mangle(self.namespace),
                mangle(self.name),
            )
        )

    def token(self) -> str:
        """The node's liveliness key."""
        return self._head(self.node_id, NODE)

    def entity_token(
        self, entity_id: int, kind: str, topic: str, msgtype: str, qos: str = DEFAULT_QOS
    ) -> str:
        """The liveliness key of a publisher (MP), subscription (MS) or service server
        (SS, `msgtype` the service type) of this node; DEFAULT_QOS is also the services'
        default profile (reliable, volatile, keep last 10)."""
        tail = (mangle(topic), mangle(dds_type_name(msgtype)), type_hash(msgtype), qos)
        return "/".join((self._head(entity_id, kind), *tail))


def gid(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh derives from an entity's liveliness key."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence_number: int, source_timestamp: int, source_gid: bytes) -> bytes:
    return _ATTACHMENT.pack(sequence_number, source_timestamp, GID_SIZE, source_gid)


def read_attachment(raw: bytes | None) -> Attachment:
    """The attachment of a sample; WireError if it is missing or not rmw_zenoh's."""
    if raw is None:
        raise WireError("no attachment (rmw_zenoh sends sequence number, timestamp, gid)")
    if len(raw) != _ATTACHMENT.size:
        raise WireError(
            f"attachment of {len(raw)} bytes; rmw_zenoh's has {_ATTACHMENT.size} "
            "(int64 sequence number, int64 timestamp, 16-byte gid)"
        )
    sequence, stamp, size, source = _ATTACHMENT.unpack(raw)
    if size != GID_SIZE:
        raise WireError(f"attachment gid length {size}, expected {GID_SIZE}")
    return Attachment(sequence, stamp, source)


class Pending:
    """Service requests taken and not yet answered, by (client GID, sequence number):
    rmw_zenoh takes no second request of a pair still pending.  Thread-safe."""

    def __init__(self) -> None:
        self._taken: set[tuple[bytes, int]] = set()
        self._lock = threading.Lock()

    def take(self, request: Attachment) -> None:
        """Note `request` taken; WireError if its pair is pending."""
        pair = (request.source_gid, request.sequence_number)
        with self._lock:
            if pair in self._taken:
                raise WireError("duplicate sequence number")
            self._taken.add(pair)

    def done(self, request: Attachment) -> None:
        with self._lock:
            self._taken.discard((request.source_gid, request.sequence_number))


def take_request(
    query: zenoh.Query, reqtype: str | None, max_bytes: int, pending: Pending
) -> tuple[Any, Attachment]:
    """A service request as rmw_zenoh's ServiceData::take_request takes it: its payload
    decoded as `reqtype` (or its bytes, None: decoded later), and its attachment, noted
    in `pending` until respond(); WireError, the query to be dropped unanswered, for a
    payload above `max_bytes`, CDR that does not read, an attachment that is missing or
    malformed or has a negative sequence number or timestamp, or a pair still pending."""
    payload, extra = query.payload, query.attachment
    size = 0 if payload is None else len(payload)
    if size > max_bytes:
        raise WireError(f"a request of {size} bytes, above {max_bytes}")
    raw = b"" if payload is None else payload.to_bytes()
    msg = raw if reqtype is None else deserialize(raw, reqtype)
    request = read_attachment(None if extra is None else extra.to_bytes())
    if request.sequence_number < 0 or request.source_timestamp < 0:
        raise WireError("negative sequence number or timestamp")
    pending.take(request)
    return msg, request


def request_server(
    key: str,
    reqtype: str | None,
    max_bytes: int,
    pending: Pending,
    taken: Callable[[zenoh.Query, Any, Attachment], None],
) -> Callable[[zenoh.Query], None]:
    """The queryable callback (zenoh's thread) of service `key`: each request taken as
    take_request takes it and handed to `taken(query, msg, request)`, or dropped
    unanswered, as rmw_zenoh drops what it cannot take."""

    def serve(query: zenoh.Query) -> None:
        try:
            msg, request = take_request(query, reqtype, max_bytes, pending)
        except WireError as exc:
            log.debug("ROS 2 service %s: request dropped: %s", key, exc)
            query.drop()  # the client gets no reply, as from rmw_zenoh
            return
        except Exception:
            log.exception("ROS 2 service %s: the request callback failed", key)
            query.drop()
            return
        taken(query, msg, request)

    return serve


def respond(query: zenoh.Query, key: str, response: Any, request: Attachment) -> None:
    """Answer the taken `request` with `response` (a rosbags message) as rmw_zenoh's
    ServiceData::send_response does: on the service's `key`, in CDR, the attachment with
    the request's sequence number and client GID and the server's time.  A client that
    left meanwhile is no error; the query is done with either way."""
    extra = attachment(request.sequence_number, time.time_ns(), request.source_gid)
    try:
        query.reply(key, serialize(response), attachment=extra)
    except zenoh.ZError:  # the client gave up (timeout) or left
        log.debug("ROS 2 service %s: the client left before the reply", key)
    finally:
        with contextlib.suppress(zenoh.ZError):
            query.drop()


_PEEKED_NAMES = 64  # joint names read past at most; more: left to the full decoding


def sequence_length(raw: bytes, msgtype: str, skip: int = 0) -> int | None:
    """The number of poses a nav_msgs/msg/Path, or of points a
    trajectory_msgs/msg/MultiDOFJointTrajectory, declares, read from the first bytes of
    its CDR without decoding it (so that too long a one is refused at the cost of a few
    reads), after `skip` bytes (an action goal's 16-byte id before its Path); None where
    those bytes do not read so (the full decoding names why).

    Both begin with a std_msgs/msg/Header (stamp: int32 + uint32; frame_id: uint32
    length with the NUL, the bytes); a MultiDOFJointTrajectory then has joint_names
    (uint32 count, each a string); then the sequence's uint32 count.  CDR aligns each
    uint32 to 4 bytes from the end of the 4-byte encapsulation header."""
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        return None
    u32 = struct.Struct("<I" if raw[1] == 1 else ">I")
    at = 4 + skip + 8  # the stamp
    names = 0

    def read() -> int | None:
        nonlocal at
        at += -(at - 4) % 4
        if at + 4 > len(raw):
            return None
        at += 4
        return u32.unpack_from(raw, at - 4)[0]

    def skip_string() -> bool:
        nonlocal at
        size = read()
        at += size if size is not None else len(raw)
        return at <= len(raw)

    if not skip_string():
        return None
    if msgtype == "trajectory_msgs/msg/MultiDOFJointTrajectory":
        names = read()
        if names is None or names > _PEEKED_NAMES:
            return None
        for _ in range(names):
            if not skip_string():
                return None
    return read()


def message(msgtype: str, **fields: Any) -> Any:
    """A rosbags message object of `msgtype`."""
    return TYPESTORE.types[msgtype](**fields)


def serialize(msg: Any) -> bytes:
    """`msg` in little-endian CDR with its encapsulation header."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def deserialize(raw: bytes, msgtype: str) -> Any:
    """A CDR payload of `msgtype`; WireError naming the problem for anything else
    (no CDR header, truncated, a sequence longer than the payload, bad strings,
    trailing bytes)."""
    try:
        return TYPESTORE.deserialize_cdr(raw, msgtype)
    except Exception as exc:  # rosbags' own errors, and any a hostile payload provokes
        raise WireError(f"malformed CDR for {msgtype}: {type(exc).__name__}: {exc}") from None
