"""Bus load per bus of the 8 CiA 402 drives of reference8 spread over several buses, from
the bus-load model (sim_bus.bus.busload, worst-case bit stuffing unless told otherwise).

One cycle on a bus is what the daemon and the drives put on it: the SYNC the daemon's
driver sends, one torque command (RPDO1) per drive, and each drive's answer to the SYNC
(TPDO1 statusword + position + mode, TPDO2 velocity).  The frames are the real ones: the
host driver's SYNC and commands for a multi-bus config, the codec's TPDOs (heartbeats,
10 per second per drive, add about 0.2 % and are left out).

    python bench/busload.py [--json] [--bitrate 1000000]

Prints `{N}_buses_{rate}hz_max_load` (the most loaded bus, a fraction of the bit time)
for 1, 2 and 4 buses at 500 and 1000 Hz, the bits one cycle puts on the most loaded bus
(`..._bits_per_cycle`), the fastest rate each layout allows at the issue's load goals
(`..._max_rate_hz_at_{goal}`), and the same loads with expected and no stuffing for
reference.  `..._compact_pdo` is the load of the smallest mapping a CiA 402 host could
configure for a cycle (issue 15): per drive a 2-byte RPDO (target torque; controlword
sent only when it changes) and one 8-byte TPDO (position and velocity actual;
statusword on change), worst-case stuffing.  No timing is involved: the figures are the
model's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import can

from daemon.config import DaemonConfig, load_config
from drivers.cia402 import codec
from drivers.factory import make_driver
from drivers.multibus import MultiBusDriver
from sim_bus.bus.busload import Stuffing, cycle_load

CONFIG = Path(__file__).resolve().parent.parent / "config" / "reference8-cia402.yaml"
LAYOUTS = (1, 2, 4)  # buses the 8 drives are spread over, evenly
RATES = (500, 1000)
GOALS = {2: 0.70, 4: 0.40}  # issue 18: most loaded bus at 1 kHz, 2 and 4 buses


def spread(buses: int, bitrate: int) -> DaemonConfig:
    """reference8-cia402 with its 8 drives spread evenly over `buses` buses (node ids
    1.. on each), at `bitrate`."""

    def edit(data: dict) -> None:
        names = [f"can{k}" for k in range(buses)]
        data["can"] = [{"channel": name, "bitrate": bitrate} for name in names]
        per = 8 // buses
        data["drives"]["bus"] = [names[i // per] for i in range(8)]
        data["drives"]["nodes"] = [1 + i % per for i in range(8)]

    return load_config(CONFIG, edit)


def cycle_frames(config: DaemonConfig) -> dict[str, list[can.Message]]:
    """One cycle's frames on each bus, by bus name."""
    driver = make_driver(config.drives, config.robot)
    out: dict[str, list[can.Message]] = {}
    parts = driver.parts if isinstance(driver, MultiBusDriver) else None
    sent = driver.cycle_start() + driver.commands([100.0] * driver.n)
    for msg in sent:
        out.setdefault(msg.channel or config.buses[0].bus_name, []).append(msg)
    for i, (node, bus) in enumerate(
        zip(config.drives.nodes, config.drives.bus_names(), strict=True)
    ):
        name = bus or config.buses[0].bus_name
        position = round(driver.scalings[i].position(2.0))
        out[name] += [
            codec.encode_tpdo1(node, 0x1237, position, 10),
            codec.encode_tpdo2(node, -12345),
        ]
    assert parts is None or len(out) == len(parts)
    return out


def loads(buses: int, bitrate: int) -> dict[str, float]:
    frames = cycle_frames(spread(buses, bitrate))
    result: dict[str, float] = {}
    stuffings: tuple[Stuffing, ...] = ("worst", "expected", "none")
    for stuffing in stuffings:
        worst = max(
            (cycle_load(f, 1.0, bitrate, stuffing) for f in frames.values()),
            key=lambda load: load.bits_per_cycle,
        )
        tail = "" if stuffing == "worst" else f"_{stuffing}_stuffing"
        if stuffing == "worst":
            result[f"{buses}_buses_bits_per_cycle"] = round(worst.bits_per_cycle, 1)
        for rate in RATES:
            load = worst.bits_per_cycle * rate / bitrate
            result[f"{buses}_buses_{rate}hz_max_load{tail}"] = round(load, 4)
        if stuffing == "worst":
            for goal in sorted(set(GOALS.values())):
                rate = goal * bitrate / worst.bits_per_cycle
                result[f"{buses}_buses_max_rate_hz_at_{goal:.2f}"] = round(rate, 1)
    return result


def compact_loads(buses: int, bitrate: int) -> dict[str, float]:
    """The most loaded bus with the compact mapping (the module's doc), worst stuffing."""
    per = 8 // buses
    frames = [codec.encode_sync()]
    for node in range(1, per + 1):
        frames.append(can.Message(arbitration_id=0x200 + node, data=bytes(2), is_extended_id=False))
        frames.append(can.Message(arbitration_id=0x180 + node, data=bytes(8), is_extended_id=False))
    bits = cycle_load(frames, 1.0, bitrate, "worst").bits_per_cycle
    return {
        f"{buses}_buses_{rate}hz_max_load_compact_pdo": round(bits * rate / bitrate, 4)
        for rate in RATES
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--bitrate", type=int, default=1_000_000, help="bit/s of every bus")
    args = parser.parse_args(argv)
    results: dict[str, float | bool] = {"bitrate": args.bitrate, "drives": 8}
    for buses in LAYOUTS:
        results.update(loads(buses, args.bitrate))
        results.update(compact_loads(buses, args.bitrate))
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
