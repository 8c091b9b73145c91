"""Bus load per bus of the 8 CiA 402 drives of reference8 spread over several buses, from
the bus-load model (sim_bus.bus.busload, worst-case bit stuffing unless told otherwise)
applied to the configured host driver and drive profile (sim_bus.bus.cycle_frames).

One cycle on a bus is what the daemon and the drives put on it in steady state: the SYNC
the daemon's driver sends, its torque commands, and each drive's TPDOs on SYNC; the
heartbeats (the host's and each drive's, every heartbeat_period) at their own rate.  Two
PDO layouts:

- default: per drive RPDO1 controlword + target torque + mode, TPDO1 statusword +
  position + mode display and TPDO2 velocity on SYNC;
- compact (config/reference8-cia402-2bus.yaml's drives.profile, CiA 301 only): one
  shared 8-byte RPDO per bus with every drive's target torque (dummy entries over the
  others' bytes), controlword and mode in an RPDO sent on change, TPDO1 position actual
  alone on SYNC, statusword and mode display on change; the host differentiates
  positions.  It needs at most 4 drives per bus (4 x 2 bytes of torque).

    python bench/busload.py [--json] [--bitrate 1000000]

Prints `{N}_buses_{rate}hz_max_load` (the most loaded bus, a fraction of the bit time)
for 1, 2 and 4 buses at 500 and 1000 Hz with the best layout the bus allows (named in
`{N}_buses_layout`), and for each layout `..._{layout}_layout`: the same load, the bits
one cycle puts on the most loaded bus (`{N}_buses_bits_per_cycle_{layout}_layout`), the
fastest rate at the issue's load goals (`{N}_buses_max_rate_hz_at_{goal}_{layout}_layout`),
and the load with expected and no stuffing for reference.  No timing is involved: the
figures are the model's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cdpr import ConfigError
from cdpr.description import load_yaml
from daemon.config import DaemonConfig, load_config
from sim_bus.bus.busload import Stuffing
from sim_bus.bus.cycle_frames import bus_cycles

CONFIGS = Path(__file__).resolve().parent.parent / "config"
CONFIG = CONFIGS / "reference8-cia402.yaml"
COMPACT = CONFIGS / "reference8-cia402-2bus.yaml"  # its drives.profile: the compact layout
LAYOUTS = ("compact", "default")
BUSES = (1, 2, 4)  # buses the 8 drives are spread over, evenly
RATES = (500, 1000)
GOALS = {2: 0.70, 4: 0.40}  # most loaded bus at 1 kHz, 2 and 4 buses


def spread(buses: int, bitrate: int, layout: str) -> DaemonConfig:
    """reference8-cia402 with its 8 drives spread evenly over `buses` buses (node ids
    1.. on each), at `bitrate`, with the PDO `layout`; ConfigError if the layout cannot
    serve that many drives per bus."""
    compact = load_yaml(COMPACT)

    def edit(data: dict) -> None:
        names = [f"can{k}" for k in range(buses)]
        data["can"] = [{"channel": name, "bitrate": bitrate} for name in names]
        per = 8 // buses
        data["drives"]["bus"] = [names[i // per] for i in range(8)]
        data["drives"]["nodes"] = [1 + i % per for i in range(8)]
        if layout == "compact":
            data["drives"]["profile"] = compact["drives"]["profile"]
            data["controller"]["velocity"] = compact["controller"]["velocity"]

    return load_config(CONFIG, edit)


def loads(buses: int, bitrate: int, layout: str) -> dict[str, float]:
    """The figures of one layout (module docstring), keys ending in `_{layout}_layout`."""
    config = spread(buses, bitrate, layout)
    cycles = bus_cycles(config.drives, config.robot, config.buses)
    result: dict[str, float] = {}
    stuffings: tuple[Stuffing, ...] = ("worst", "expected", "none")
    tail = f"_{layout}_layout"
    for stuffing in stuffings:
        extra = "" if stuffing == "worst" else f"_{stuffing}_stuffing"
        for rate in RATES:
            worst = max(bus.load(rate, stuffing) for bus in cycles)
            result[f"{buses}_buses_{rate}hz_max_load{extra}{tail}"] = round(worst, 4)
    result[f"{buses}_buses_bits_per_cycle{tail}"] = max(c.bits_per_cycle() for c in cycles)
    for goal in sorted(set(GOALS.values())):
        rate = min(bus.max_rate_hz(goal) for bus in cycles)
        result[f"{buses}_buses_max_rate_hz_at_{goal:.2f}{tail}"] = round(rate, 1)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--bitrate", type=int, default=1_000_000, help="bit/s of every bus")
    args = parser.parse_args(argv)
    results: dict[str, float | bool | str] = {"bitrate": args.bitrate, "drives": 8}
    for buses in BUSES:
        possible = []
        for layout in LAYOUTS:
            try:
                figures = loads(buses, args.bitrate, layout)
            except ConfigError as exc:  # the compact layout: more than 4 drives per bus
                problem = str(exc).split(": ", 1)[-1]  # without the config file's path
                results[f"{buses}_buses_{layout}_layout"] = f"not possible: {problem}"
                continue
            results.update(figures)
            possible.append(layout)
        best = min(
            possible, key=lambda name: results[f"{buses}_buses_1000hz_max_load_{name}_layout"]
        )
        results[f"{buses}_buses_layout"] = best
        for rate in RATES:
            key = f"{buses}_buses_{rate}hz_max_load"
            results[key] = results[f"{key}_{best}_layout"]
    for buses, goal in GOALS.items():
        results[f"{buses}_buses_1000hz_goal_met"] = (
            results[f"{buses}_buses_1000hz_max_load"] <= goal
        )
    if args.json:
        print(json.dumps(results))
    else:
        for key, value in results.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
