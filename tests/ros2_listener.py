"""A ROS 2 node's subscriptions to everything a domain publishes, on rmw_zenoh's key
format (tests/data/rmw_zenoh_reference.md: <domain>/<topic>/<DDS type name>/<type hash>),
written from rmw_zenoh's design, not from the daemon's encoder: each sample's type read
from its key and its CDR decoded with rosbags (bench/loop.py --view's ROS 2 side).

`python -m tests.ros2_listener PORT DOMAIN SECONDS`: connected to tcp/127.0.0.1:PORT,
prints how many samples arrived and decoded so far once a second; may be stopped at
any time."""

from __future__ import annotations

import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore

from tests.loopback import zenoh_peer

STORE = get_typestore(Stores.ROS2_JAZZY)


def message_type(key: str) -> str:
    """geometry_msgs::msg::dds_::PoseStamped_ (the key's third-last chunk) ->
    geometry_msgs/msg/PoseStamped."""
    package, kind, _dds, name = key.split("/")[-2].split("::")
    return f"{package}/{kind}/{name.removesuffix('_')}"


def listen(port: int, domain: int, seconds: float) -> None:
    decoded = 0
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal decoded
        STORE.deserialize_cdr(sample.payload.to_bytes(), message_type(str(sample.key_expr)))
        with lock:
            decoded += 1

    session = zenoh_peer(port)
    try:
        session.declare_subscriber(f"{domain}/**", on_sample)
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(left, 1.0))
            with lock:
                print(decoded, flush=True)
    finally:
        session.close()


if __name__ == "__main__":
    listen(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]))
