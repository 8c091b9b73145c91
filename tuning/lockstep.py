"""Lock-step co-simulation: a controller callback driving a simulated plant.

Simulated time only: each control cycle at t_k = k / rate_hz the runner reads the
drives' measurements, calls ``controller(t_k, lengths, rates)``, and the drives apply
the returned force commands at t_k + ``latency`` (default at once; a whole number of
plant steps) and hold them (zero-order hold) until the next ones take effect; until
the first one does, the plant's held commands stay.  The plant advances by whole plant
steps.  Deterministic, and as fast as the plant steps.  Each cycle records the plant's
true state at t_k (after the commands due then took effect) with the measurement and
the commands, for tests and tools.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr import Pose
from sim_bus.plant.config import PlantConfig

Array = NDArray[np.float64]
Controller = Callable[[float, Array, Array], ArrayLike]


class Simulated(Protocol):
    """What the runner needs of a plant (sim_bus.plant: Plant, rig.SingleActuatorRig)."""

    config: PlantConfig
    time: float

    @property
    def commands(self) -> Array: ...

    def measure(self) -> tuple[Array, Array]: ...

    def set_commands(self, commands: ArrayLike) -> None: ...

    def step(self) -> None: ...

    def snapshot(self) -> dict[str, Sequence[float]]: ...


class Recording:
    """Time series of a run, one row per control cycle: ``t`` (s), ``measured_lengths``
    and ``measured_rates`` (what the controller saw), ``commands`` (what it returned),
    ``applied`` (what the drives held at t_k: delayed and saturated), and the
    plant's true state (Plant: position, quaternion, twist, lengths, rates,
    cable_lengths, tensions, forces).  Every series is a numpy array, read as an
    attribute or by name."""

    def __init__(self, series: dict[str, Array]) -> None:
        self.series = series

    def __getattr__(self, name: str) -> Array:
        try:
            return self.__dict__["series"][name]
        except KeyError:
            raise AttributeError(f"recording has no series {name!r}") from None

    def __getitem__(self, name: str) -> Array:
        return self.series[name]

    def __len__(self) -> int:
        return len(self.series["t"])

    def pose(self, i: int) -> Pose:
        """The true platform pose of cycle i (plant recordings)."""
        return Pose(self.series["position"][i], self.series["quaternion"][i])

    def save(self, path: str | Path) -> None:
        """Write every series to a .npz file."""
        np.savez_compressed(path, **self.series)

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        """Read a recording written by save()."""
        with np.load(path) as data:
            return cls({name: data[name] for name in data.files})


def run_lockstep(
    plant: Simulated,
    controller: Controller,
    duration: float,
    rate_hz: float,
    latency: float = 0.0,
) -> Recording:
    """Run `controller` at `rate_hz` on `plant` for `duration` seconds of simulated
    time, its commands applied `latency` seconds late (see the module docstring);
    returns the Recording."""
    step = plant.config.step
    steps_per_cycle = round(1.0 / (rate_hz * step))
    if steps_per_cycle < 1 or abs(steps_per_cycle * step * rate_hz - 1.0) > 1e-9:
        raise ValueError(
            f"the control period 1/{rate_hz} s is not a whole number of {step} s plant steps"
        )
    late_steps = round(latency / step) if math.isfinite(latency) else -1
    if late_steps < 0 or abs(late_steps * step - latency) > 1e-9:
        raise ValueError(
            f"latency must be a whole number (>= 0) of {step} s plant steps, got {latency}"
        )
    cycles = round(duration * rate_hz)
    pending: deque[tuple[int, list[float]]] = deque()  # (plant step due, commands)
    rows: dict[str, list[Any]] = {
        "t": [],
        "measured_lengths": [],
        "measured_rates": [],
        "commands": [],
        "applied": [],
    }
    for k in range(cycles):
        t = plant.time
        lengths, rates = plant.measure()
        commands = np.asarray(controller(t, lengths, rates), dtype=float).reshape(-1).tolist()
        pending.append((k * steps_per_cycle + late_steps, commands))
        for j in range(k * steps_per_cycle, (k + 1) * steps_per_cycle):
            while pending and pending[0][0] <= j:
                plant.set_commands(pending.popleft()[1])
            if j == k * steps_per_cycle:
                rows["t"].append(t)
                rows["measured_lengths"].append(lengths)
                rows["measured_rates"].append(rates)
                rows["commands"].append(commands)
                rows["applied"].append(plant.commands)
                for name, value in plant.snapshot().items():
                    rows.setdefault(name, []).append(value)
            plant.step()
    return Recording({name: np.array(values, dtype=float) for name, values in rows.items()})
