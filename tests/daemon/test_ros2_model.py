"""The robot for RViz over rmw_zenoh's wire format, seen by a subscriber written here from
rmw_zenoh's sources (tests/data/rmw_zenoh_reference.md), not from the project's encoder:
keys and liveliness tokens spelled out, the 33-byte attachment unpacked with struct, CDR
decoded by rosbags.

A transient-local publisher is what rmw_zenoh_cpp declares (an AdvancedPublisher with a
cache of its depth): a subscription that joins after the sample was published, declared
as rmw_zenoh declares a transient-local one (an AdvancedSubscriber whose history detects
late publishers), still gets the last sample, and the liveliness token carries the
transient-local QoS.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable

import zenoh
import zenoh.ext as ze
from rosbags.typesys import Stores, get_typestore

from daemon.config.zenoh_config import ZenohSettings, build_zenoh_config, client_zenoh_config
from daemon.interface import ros2_wire as wire
from daemon.interface.ros2_bridge import _Publisher
from tests.daemon.test_zenoh_io import WAIT
from tests.loopback import free_port

JAZZY = get_typestore(Stores.ROS2_JAZZY)
STRING = "std_msgs/msg/String"
STRING_KEY = (  # <type name>/<type hash> of std_msgs/msg/String (design.md's example)
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
LATCHED_QOS = ":1:,1:,:,:,,"  # reliable, TRANSIENT_LOCAL (1), keep last 1 (the reference)


class LateSubscription:
    """A transient-local subscription as rmw_zenoh_cpp declares one
    (rmw_subscription_data.cpp): an AdvancedSubscriber with subscriber detection, a
    history of `depth` samples that detects late publishers, and heartbeat recovery;
    each sample kept as (payload bytes, attachment fields)."""

    def __init__(self, session: zenoh.Session, key: str, depth: int) -> None:
        self.samples: list[tuple[bytes, tuple[int, int, int, bytes]]] = []
        self.lock = threading.Lock()
        self.subscriber = ze.declare_advanced_subscriber(
            session,
            key,
            self._on_sample,
            history=ze.HistoryConfig(detect_late_publishers=True, max_samples=depth),
            recovery=ze.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        extra = sample.attachment
        assert extra is not None, "rmw_zenoh drops a sample without an attachment"
        fields = struct.unpack("<qqB16s", extra.to_bytes())  # seq, stamp, 16, gid
        with self.lock:
            self.samples.append((sample.payload.to_bytes(), fields))

    def wait(self, count: int = 1) -> list[tuple[bytes, tuple[int, int, int, bytes]]]:
        wait_until(lambda: len(self.samples) >= count, f"{count} samples")
        with self.lock:
            return list(self.samples)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def listening_session() -> tuple[zenoh.Session, str]:
    """A peer session listening on a free loopback port (multicast and gossip off)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return zenoh.open(build_zenoh_config(ZenohSettings(listen=[endpoint]), "cdpr/test")), endpoint


def test_a_transient_local_publisher_serves_a_subscription_that_joins_later() -> None:
    server, endpoint = listening_session()
    late = None
    try:
        zid = str(server.info.zid())
        node = wire.Node(0, zid, 0, "/", "cdprd")
        publisher = _Publisher(server, node, 4, "/latched", STRING, depth=1, transient_local=True)
        assert publisher.token == (
            f"@ros2_lv/0/{zid}/0/4/MP/%/%/cdprd/%latched/{STRING_KEY}/{LATCHED_QOS}"
        )
        for text in ("first", "second"):
            publisher.put(JAZZY.types[STRING](data=text))
        late = zenoh.open(client_zenoh_config([endpoint]))
        subscription = LateSubscription(late, f"0/latched/{STRING_KEY}", depth=1)
        ((payload, (sequence, stamp, size, gid)),) = subscription.wait()
        assert JAZZY.deserialize_cdr(payload, STRING).data == "second"  # the cache's depth: 1
        assert (sequence, size, gid) == (2, 16, wire.gid(publisher.token))
        assert 0 < time.time_ns() - stamp < WAIT * 1e9
        publisher.put(JAZZY.types[STRING](data="third"))  # then live, as any subscriber
        assert JAZZY.deserialize_cdr(subscription.wait(2)[1][0], STRING).data == "third"
        publisher.publisher.undeclare()
    finally:
        if late is not None:
            late.close()
        server.close()
