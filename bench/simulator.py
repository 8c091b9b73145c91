"""What the simulated drives cost per control cycle: `cdprd run --sim`'s simulator
process (8 drives of config/reference8-<protocol>.yaml on the true plant) answering the
host's driver, brought up and enabled over CAN frames and holding the platform at its
static tensions, in lock-step (tuning.can_lockstep: simulated time, no bus, no wall
clock), so the figures are the simulator's own work, whatever else loads the host.

    python bench/simulator.py [--json] [--seconds 4] [--rate 1000] [--protocol cia402]

- `cycle`: median / p99 (us) of the simulator's CPU time per control cycle (every frame
  the host sends and every plant step in the cycle), time.thread_time_ns;
- `sync_answer`: median / p99 (us) of the CPU time from a SYNC's delivery to the drives'
  answers to it (CiA 402; the SYNC-less ODrive: the cycle's frames): what a SYNC waits
  in the simulator before its feedback leaves, on top of the host's scheduling;
- `core_fraction`: the cycle's median x rate, the share of a core the simulator takes.
The host's side (driver encode/decode) is not counted.  Compare medians of several runs.
"""

from __future__ import annotations

import argparse
import gc
import json
import time
from pathlib import Path

import numpy as np
from timing import summary_us

from cdpr.controller import static_tensions, tension_solver
from daemon.cli.simulated import sim_section, simulated_robot
from daemon.config import load_config
from drivers.factory import protocol_driver
from tuning.can_lockstep import LockstepLink, bring_up

CONFIGS = Path(__file__).resolve().parent.parent / "config"


def measure(protocol: str, rate_hz: float, seconds: float) -> dict:
    config = load_config(CONFIGS / f"reference8-{protocol}.yaml")
    robot = config.robot
    sim = simulated_robot(config, sim_section(config))  # as the simulator process builds it
    driver = protocol_driver(config.drives, config.drives.scalings_for(robot))
    link = LockstepLink(sim, driver)
    tension = tension_solver(robot, config.controller)
    forces = (-static_tensions(robot, tension, robot.home)).tolist()
    period = 1.0 / rate_hz
    bring_up(link, forces, period)
    clock = time.thread_time_ns
    spent = [0]

    def timed(method):
        def call(*args):
            t0 = clock()
            try:
                return method(*args)
            finally:
                spent[0] += clock() - t0

        return call

    sim.handle, sim.advance_to = timed(sim.handle), timed(sim.advance_to)
    cycles = round(seconds * rate_hz)
    cycle_ns, sync_ns = np.empty(cycles), np.empty(cycles)
    gc.collect()
    for k in range(cycles):
        spent[0] = 0
        link.advance(link.t + period)
        for frame in driver.cycle_start():
            link.send(frame)
        sync_ns[k] = spent[0]
        link.deliver()
        for frame in driver.commands(forces):
            link.send(frame)
        link.deliver()
        cycle_ns[k] = spent[0]
    states = {s.state.name for s in driver.status}
    return {
        "protocol": protocol,
        "rate_hz": rate_hz,
        "cycles": cycles,
        "drives": sim.n,
        "drive_states": sorted(states),
        "cycle": summary_us(cycle_ns),
        "sync_answer": summary_us(sync_ns),
        "core_fraction": round(float(np.median(cycle_ns)) * 1e-9 * rate_hz, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--seconds", type=float, default=4.0, help="simulated seconds held")
    parser.add_argument("--rate", type=float, default=1000.0, help="control rate (Hz)")
    parser.add_argument("--protocol", choices=("cia402", "odrive"), default=None,
                        help="one protocol (default: both)")  # fmt: skip
    args = parser.parse_args()
    protocols = [args.protocol] if args.protocol else ["cia402", "odrive"]
    out = {p: measure(p, args.rate, args.seconds) for p in protocols}
    if args.json:
        print(json.dumps(out))
        return
    for p, r in out.items():
        print(
            f"{p:7s} {r['rate_hz']:g} Hz, {r['drives']} drives {'/'.join(r['drive_states'])}: "
            f"cycle {r['cycle']['median_us']} us (p99 {r['cycle']['p99_us']}), "
            f"SYNC answered after {r['sync_answer']['median_us']} us "
            f"(p99 {r['sync_answer']['p99_us']}), {r['core_fraction']} of a core"
        )


if __name__ == "__main__":
    main()
