"""The ROS 2 bridge's std_srvs/srv/Trigger services (enable, hold, brake, reset, disable)
and std_srvs/srv/SetBool services (hold_observer, freeze_payload) called as an
rmw_zenoh_cpp client calls them, by a client written here from rmw_zenoh's
design document and sources (tests/data/rmw_zenoh_reference.md, "Service servers" and
"Service type hashes"), not from the project's encoder: the key and the liveliness token
spelled out from the reference, the 33-byte attachment packed with struct, the request's
CDR written byte by byte, the reply decoded with rosbags' deserializer from the .srv text.

Against the zenoh interface's stand-in handler (test_zenoh_io.Running, the bridge on its
session): each service runs its command and answers success and the reply or the refusal,
with rmw_zenoh's reply attachment; requests rmw_zenoh's server would not take (no or a bad
attachment, malformed CDR, a repeated pending sequence number) get no reply and reach no
handler; a wrong type hash reaches no queryable; a flood passes the template's `cmd/*`
limit only.  Against `cdprd run --sim` (slow): the simulated robot enables, brakes, resets,
holds and disables from ROS 2, and bad requests leave it where it was.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings
from daemon.interface.ros2_bridge import ingress_limits
from tests.daemon.test_ros2_process import (
    DOMAIN,
    NAMESPACE,
    PREFIX,
    _listening,
    wait,
)
from tests.daemon.test_zenoh_io import WAIT, Running, StandIn, template_zenoh
from tests.loopback import free_port, zenoh_peer
from tests.processes import CONFIG, ROOT, finish, start_daemon

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "rmw_zenoh_reference.md"
# Jazzy's RIHS01 hash of the service type std_srvs/srv/Trigger (the reference's sources)
TRIGGER_HASH = "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
TRIGGER_DDS = "std_srvs::srv::dds_::Trigger_"
SET_BOOL_HASH = "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a"
SET_BOOL_DDS = "std_srvs::srv::dds_::SetBool_"
# std_srvs/srv/Trigger_Request: no field but rosidl's placeholder uint8; CDR little endian
REQUEST = bytes([0x00, 0x01, 0x00, 0x00]) + bytes([0])
QOS = "::,10:,:,:,,"  # rmw_qos_profile_services_default: reliable, volatile, keep last 10
SERVICES = ("enable", "hold", "brake", "reset", "disable")
CLIENT_GID = bytes(range(100, 116))
ROS2 = Ros2Settings(enabled=True, rate_hz=20.0)  # domain 0, namespace /
STEPS = (  # label, service: the simulated robot's run
    ("enable", "enable"),
    ("disable", "disable"),
    ("again", "enable"),
    ("brake", "brake"),
    ("reset", "reset"),
)

_STORE = get_typestore(Stores.EMPTY)  # the Response as Trigger.srv (and SetBool.srv) declare it
_STORE.register(get_types_from_msg("bool success\nstring message", "std_srvs/msg/Trigger_Response"))


def service_key(name: str, domain: int = 0, type_hash: str = TRIGGER_HASH) -> str:
    """<domain_id>/<fully qualified name>/<type name>/<type hash> (design.md)."""
    return f"{domain}/{name.strip('/')}/{TRIGGER_DDS}/{type_hash}"


def set_bool_key(name: str, domain: int = 0) -> str:
    return f"{domain}/{name.strip('/')}/{SET_BOOL_DDS}/{SET_BOOL_HASH}"


def set_bool(data: bool) -> bytes:
    """std_srvs/srv/SetBool_Request (bool data) in little-endian CDR."""
    return bytes([0x00, 0x01, 0x00, 0x00, int(data)])


def request_attachment(sequence: int, gid: bytes = CLIENT_GID, stamp: int | None = None) -> bytes:
    """int64 sequence number, int64 ns timestamp, the GID's length (16) and its bytes."""
    return struct.pack("<qqB16s", sequence, time.time_ns() if stamp is None else stamp, 16, gid)


def call(
    session: zenoh.Session,
    key: str,
    payload: bytes = REQUEST,
    attachment: bytes | None = None,
    timeout: float = WAIT,
) -> list[zenoh.Reply]:
    """One request as rmw_zenoh's ClientData::send_request makes it: a get on the
    service's key, every complete queryable, no consolidation."""
    replies = session.get(
        key,
        payload=payload,
        attachment=attachment,
        target=zenoh.QueryTarget.ALL_COMPLETE,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )
    return list(replies)


def response(reply: zenoh.Reply) -> tuple[Any, tuple[int, int, int, bytes]]:
    """The Response decoded with rosbags, and the reply attachment's four fields."""
    assert reply.ok is not None, reply.err
    msg = _STORE.deserialize_cdr(reply.ok.payload.to_bytes(), "std_srvs/msg/Trigger_Response")
    extra = reply.ok.attachment
    assert extra is not None
    return msg, struct.unpack("<qqB16s", extra.to_bytes())


def trigger(session: zenoh.Session, key: str, sequence: int, payload: bytes = REQUEST) -> Any:
    """A well-formed call: its Response, after checking the reply attachment."""
    before = time.time_ns()
    (reply,) = call(session, key, payload, request_attachment(sequence))
    msg, (echoed, stamp, size, gid) = response(reply)
    assert str(reply.ok.key_expr) == key
    assert (echoed, size, gid) == (sequence, 16, CLIENT_GID)
    assert before <= stamp <= time.time_ns()  # the server's own time, not the request's
    return msg


def test_the_reference_holds_the_trigger_hash() -> None:
    assert TRIGGER_HASH in REFERENCE.read_text()


def test_each_trigger_service_runs_its_command_and_answers() -> None:
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    try:
        refused = trigger(s, service_key("/enable"), 1)
        assert refused.success is False
        assert refused.message == "invalid_state: cannot enable while BRAKED (reset first)"
        handler.refuse_enable = False
        for sequence, name in enumerate(SERVICES, start=2):
            msg = trigger(s, service_key(f"/{name}"), sequence)
            assert msg.success is True, msg
            expected = '{"state":"IDLE"}' if name == "reset" else f'"command":"{name}"'
            assert expected in msg.message
    finally:
        s.close()
        served.stop()
    assert [c for c in handler.calls if c[0] in SERVICES] == [
        ("enable", {}),
        *((name, {}) for name in SERVICES),
    ]


def test_the_services_are_under_the_namespace_and_announced_as_ss() -> None:
    ros2 = Ros2Settings(enabled=True, domain_id=DOMAIN, namespace=NAMESPACE, brake_service="/stop")
    served = Running(StandIn(), ros2=ros2)
    s = served.session()
    try:
        replies = s.liveliness().get(f"@ros2_lv/{DOMAIN}/*/*/*/SS/**", timeout=WAIT)
        tokens = sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)
        tokens = [t for t in tokens if "std_srvs::" in t]  # the action's: test_ros2_action
        msg = trigger(s, service_key("/stop", DOMAIN), 1)
    finally:
        s.close()
        served.stop()
    assert msg.success is True
    names = {"%lab%enable", "%lab%hold", "%stop", "%lab%reset", "%lab%disable"}
    set_bools = {"%lab%hold_observer", "%lab%freeze_payload"}
    assert len(tokens) == 7
    for token in tokens:
        admin, domain, _zid, node, entity, kind, enclave, ns, node_name, *tail = token.split("/")
        assert (admin, domain, node, kind, enclave, ns, node_name) == (
            "@ros2_lv",
            str(DOMAIN),
            "0",
            "SS",
            "%",
            "%lab",
            "cdprd",
        )
        assert int(entity) > 0
        if tail[0] in set_bools:
            assert tail[1:] == [SET_BOOL_DDS, SET_BOOL_HASH, QOS]
            set_bools.discard(tail[0])
            continue
        assert tail[1:] == [TRIGGER_DDS, TRIGGER_HASH, QOS]
        names.discard(tail[0])
    assert names == set_bools == set()


def test_the_set_bool_services_hold_the_observer_and_freeze_the_payload() -> None:
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    try:
        answers = [
            trigger(s, set_bool_key("/hold_observer"), 1, set_bool(True)),
            trigger(s, set_bool_key("/hold_observer"), 2, set_bool(False)),
            trigger(s, set_bool_key("/freeze_payload"), 3, set_bool(True)),
            trigger(s, set_bool_key("/freeze_payload"), 4, set_bool(False)),
        ]
        dropped = call(s, set_bool_key("/hold_observer"), REQUEST[:4], request_attachment(5))
        untyped = call(s, set_bool_key("/hold_observer"), set_bool(True), None, timeout=1.0)
    finally:
        s.close()
        served.stop()
    assert all(msg.success for msg in answers), answers
    assert '"command":"observer"' in answers[0].message
    assert (dropped, untyped) == ([], [])
    assert [c for c in handler.calls if c[0] in ("observer", "payload")] == [
        ("observer", {"held": True}),
        ("observer", {"held": False}),
        ("payload", {"frozen": True}),
        ("payload", {"frozen": False}),
    ]


@pytest.mark.parametrize(
    ("what", "payload", "attachment"),
    [
        ("no attachment", REQUEST, None),
        ("a short attachment", REQUEST, request_attachment(1)[:-1]),
        ("a gid of 15 bytes", REQUEST, request_attachment(1)[:16] + b"\x0f" + bytes(16)),
        ("a negative sequence number", REQUEST, request_attachment(-1)),
        ("a negative timestamp", REQUEST, request_attachment(1, stamp=-5)),
        ("no payload", b"", request_attachment(1)),
        ("a header only", REQUEST[:4], request_attachment(1)),
        ("no CDR header", b"\x07\x07\x07\x07\x00", request_attachment(1)),
        ("a huge payload", REQUEST + bytes(64 * 1024), request_attachment(1)),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_requests_rmw_zenoh_would_not_take_get_no_reply(
    what: str, payload: bytes, attachment: bytes | None
) -> None:
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    try:
        replies = call(s, service_key("/brake"), payload, attachment, timeout=1.0)
        assert trigger(s, service_key("/hold"), 2).success  # the service still answers
    finally:
        s.close()
        served.stop()
    assert replies == [], what
    assert [c[0] for c in handler.calls if c[0] in SERVICES] == ["hold"], what


def test_a_wrong_type_hash_reaches_no_service() -> None:
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    wrong = "RIHS01_" + "0" * 64
    try:
        replies = call(s, service_key("/brake", type_hash=wrong), attachment=request_attachment(1))
        assert call(s, service_key("/brake").replace("Trigger_", "Empty_"), timeout=1.0) == []
    finally:
        s.close()
        served.stop()
    assert replies == []
    assert [c for c in handler.calls if c[0] in SERVICES] == []


def test_a_repeated_pending_sequence_number_gets_no_second_reply() -> None:
    """rmw_zenoh refuses a request whose (client, sequence number) is still unanswered:
    reset waits for the drives (50 ms in the stand-in), so the second one comes while the
    first is pending."""
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    key = service_key("/reset")
    try:
        options = {"target": zenoh.QueryTarget.ALL_COMPLETE, "timeout": 1.0}
        first = s.get(key, payload=REQUEST, attachment=request_attachment(7), **options)
        second = s.get(key, payload=REQUEST, attachment=request_attachment(7), **options)
        answered = list(first), list(second)
    finally:
        s.close()
        served.stop()
    assert [len(replies) for replies in answered] == [1, 0]
    assert response(answered[0][0])[0].success is True
    assert [c[0] for c in handler.calls if c[0] in SERVICES] == ["reset"]


@pytest.mark.parametrize("access_control", [True, False])
def test_with_the_templates_zenoh_section_only_the_daemon_answers(access_control: bool) -> None:
    """Another local process serves the enable service too and answers with its own bytes:
    with the template's access control its queryable and replies never reach the client,
    which gets the daemon's answer alone; without it (the control case) both."""
    handler = StandIn()
    served = Running(handler, template_zenoh(access_control), ros2=ROS2)
    forger, client = served.session(), served.session()
    key = service_key("/enable")
    try:
        kept = forger.declare_queryable(key, lambda q: q.reply(key, b"forged"), complete=True)
        time.sleep(0.5)  # the declaration's way through the daemon's session
        replies = call(client, key, attachment=request_attachment(1))
        kept.undeclare()
    finally:
        forger.close()
        client.close()
        served.stop()
    payloads = sorted(r.ok.payload.to_bytes() for r in replies if r.ok is not None)
    if not access_control:
        assert len(payloads) == 2 and b"forged" in payloads
        return
    assert len(replies) == 1
    assert response(replies[0])[0].message.startswith("invalid_state: ")


def test_the_services_take_the_limit_of_their_commands() -> None:
    limited = ZenohSettings(ingress_limits_hz={"cmd/*": 20.0, "cmd/brake": 50.0})
    limits = ingress_limits(ROS2, limited)
    assert {k: v for k, v in limits.items() if TRIGGER_DDS in k} == {
        service_key("/enable"): 20.0,
        service_key("/hold"): 20.0,
        service_key("/brake"): 20.0,  # the lowest of the matching entries
        service_key("/reset"): 20.0,
        service_key("/disable"): 20.0,
    }
    held = ingress_limits(ROS2, ZenohSettings(ingress_limits_hz={"cmd/hold": 5.0}))
    assert {k: v for k, v in held.items() if TRIGGER_DDS in k} == {service_key("/hold"): 5.0}


def test_a_flood_of_requests_passes_the_templates_command_limit_only() -> None:
    """The hardware template limits `cmd/*` to 20 Hz: of thirty hold requests sent at
    once, zenoh lets one or two through, and one more for each 50 ms the sending took on a
    loaded host (the rest time out at the client, as a dropped query does); the handler
    sees no more."""
    handler = StandIn()
    served = Running(handler, template_zenoh(access_control=True), ros2=ROS2)
    s = served.session()
    key = service_key("/hold")
    try:
        began = time.monotonic()
        pending = [
            s.get(key, payload=REQUEST, attachment=request_attachment(n), timeout=2.0)
            for n in range(1, 31)
        ]
        periods = int((time.monotonic() - began) * 20.0)
        answered = sum(len(list(replies)) for replies in pending)
        time.sleep(0.1)  # past the limit's period: the next request passes
        assert trigger(s, key, 100).success
    finally:
        s.close()
        served.stop()
    assert 1 <= answered <= 2 + periods < 30
    assert len([c for c in handler.calls if c[0] == "hold"]) == answered + 1


# -- the simulated robot ----------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.host_timing
@pytest.mark.timeout(150)
def test_the_simulated_robot_is_driven_from_ros2_services(tmp_path: Path) -> None:
    """`cdprd run --sim` with ROS 2 on (domain 7, namespace /lab): hold is refused while
    idle, enable holds the robot, disable idles it, brake brakes it, reset brings it back
    to idle, each reply naming the state the command left; then requests without an
    attachment, with malformed CDR or a wrong type hash get no reply and the robot is
    not enabled."""
    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["ros2"] = {"enabled": True, "domain_id": DOMAIN, "namespace": NAMESPACE}
    # the simulated drives' feedback may come late on a loaded host (a brake on its own
    # would stop the run): this test is about the services, not about feedback timing
    data["safety"]["stale_cycles"] = 100
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    proc = start_daemon(config, "--sim")
    sequence = 0

    def key(name: str) -> str:
        return service_key(f"{NAMESPACE}/{name}", DOMAIN)

    def run(s: zenoh.Session, name: str) -> tuple[bool, str, str | None]:
        """Call `name`: success, message, the state its result names (None if refused)."""
        nonlocal sequence
        sequence += 1
        msg = trigger(s, key(name), sequence)
        state = json.loads(msg.message)["state"] if msg.success else None
        return msg.success, msg.message, state

    try:
        wait(lambda: _listening(port), 60.0, "the daemon to listen")  # a loaded host: slow
        s = zenoh_peer(port)
        states: list[str] = []
        kept = s.declare_subscriber(
            f"{PREFIX}/state", lambda x: states.append(json.loads(x.payload.to_bytes())["state"])
        )
        try:
            wait(lambda: bool(states) and states[-1] == "idle", 60.0, "idle")
            refused = run(s, "hold")
            steps = {label: run(s, name) for label, name in STEPS}
            seen = len(states)
            bad = [
                call(s, key("enable"), attachment=None, timeout=1.0),
                call(s, key("enable"), b"\x00\x01", request_attachment(500), timeout=1.0),
                call(
                    s,
                    service_key(f"{NAMESPACE}/enable", DOMAIN, "RIHS01_" + "1" * 64),
                    attachment=request_attachment(501),
                    timeout=1.0,
                ),
            ]
            time.sleep(0.5)
            after_bad = states[seen:]
        finally:
            kept.undeclare()
            s.close()
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert refused[:2] == (False, "invalid_state: cannot hold while idle (enable first)")
    assert {name: (ok, state) for name, (ok, _message, state) in steps.items()} == {
        "enable": (True, "hold"),
        "disable": (True, "idle"),
        "again": (True, "hold"),
        "brake": (True, "braked"),
        "reset": (True, "idle"),
    }, steps
    assert bad == [[], [], []]
    assert after_bad and "hold" not in after_bad, after_bad
