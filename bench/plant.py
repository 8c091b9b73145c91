"""Benchmark of the simulated plant on config/robots/reference8.yaml at the default step.

The platform moves: a drive-level PD makes each drum follow its home length plus a
few millimetres of sine (the crossed robot is unstable under constant forces; see
tests/sim_bus/test_plant.py).  Prints:

- `step_us`: median and p99 of one Plant.step() call, in microseconds;
- `realtime_factor`: simulated seconds per second spent in those Plant.step() calls;
- `lockstep_realtime_factor`: the same for a whole tuning.lockstep run at 500 Hz
  (measurement, controller, recording included; CPU time of the running thread, as
  numpy's BLAS threads may spin on the other CPU).

    python bench/plant.py [--json] [--seconds S]
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from timing import REFERENCE8, summary_us

from cdpr import Robot
from sim_bus.plant import Plant, equilibrium_tensions
from tuning.lockstep import run_lockstep

Array = NDArray[np.float64]
RATE_HZ = 500.0
KP, KD = 2e4, 400.0  # N/m, N s/m: the drives' length hold


def make_plant(robot: Robot) -> tuple[Plant, Callable[[float, Array, Array], Array]]:
    """The plant at home in equilibrium, and the drives' PD on a moving length reference."""
    plant = Plant(robot)
    hold = -equilibrium_tensions(robot, robot.home)
    home = plant.measure()[0]
    phase = np.arange(robot.n_cables)

    def controller(t: float, lengths: Array, rates: Array) -> Array:
        reference = home + 3e-3 * np.sin(2.0 * t + phase)
        speed = 6e-3 * np.cos(2.0 * t + phase)
        return hold - KP * (lengths - reference) - KD * (rates - speed)

    return plant, controller


def step_times(robot: Robot, seconds: float) -> np.ndarray:
    """Nanoseconds of each Plant.step() call; the PD runs between calls at RATE_HZ."""
    plant, controller = make_plant(robot)
    steps = round(seconds / plant.config.step)
    per_cycle = round(1.0 / (RATE_HZ * plant.config.step))
    samples = np.empty(steps)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for i in range(steps):
            if i % per_cycle == 0:
                plant.set_commands(controller(plant.time, *plant.measure()))
            t0 = clock()
            plant.step()
            samples[i] = clock() - t0
    finally:
        gc.enable()
    return samples


def lockstep_factor(robot: Robot, seconds: float) -> float:
    """Simulated seconds per CPU second of a lock-step run."""
    plant, controller = make_plant(robot)
    t0 = time.thread_time()
    run_lockstep(plant, controller, seconds, RATE_HZ)
    return seconds / (time.thread_time() - t0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    args = parser.parse_args(argv)

    robot = Robot.from_yaml(REFERENCE8)
    step_times(robot, 1.0)  # warm-up
    samples = step_times(robot, args.seconds)
    step = Plant(robot).config.step
    results = {
        "realtime_factor": round(step / (float(np.mean(samples)) / 1e9), 1),
        "step_us": summary_us(samples),
        "lockstep_realtime_factor": round(lockstep_factor(robot, args.seconds), 1),
    }
    if args.json:
        print(json.dumps(results))
    else:
        print(f"plant step          median {results['step_us']['median_us']:7.2f} us   "
              f"p99 {results['step_us']['p99_us']:7.2f} us")  # fmt: skip
        print(f"realtime factor     {results['realtime_factor']:7.1f} x (plant steps)")
        print(f"lock-step at 500 Hz {results['lockstep_realtime_factor']:7.1f} x (all included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
