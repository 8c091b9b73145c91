"""A stand-in for rmw_zenohd, the ROS 2 graph's zenoh router, as its default config
(rmw_zenoh_cpp/config/DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5) sets it up: mode router,
listening on port 7447, no multicast scouting.  Unlike it, on 127.0.0.1 only and without
gossip (the tests' loopback rule).

`python -m tests.stand_in_router ENDPOINT`: prints "ready" once it listens, runs until
its standard input closes."""

from __future__ import annotations

import json
import sys

import zenoh


def router_config(endpoint: str) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


def main() -> None:
    session = zenoh.open(router_config(sys.argv[1]))
    print("ready", flush=True)
    sys.stdin.read()
    session.close()


if __name__ == "__main__":
    main()
