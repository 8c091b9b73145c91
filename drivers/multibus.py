"""Drives spread over several CAN buses, as one driver in cable order.

One protocol driver per bus, each knowing only the nodes of its bus (so the same node id
may be on two buses), behind `MultiBusDriver`.  A frame's bus travels in its `channel`
(python-can's field for the channel a frame is sent on or came from), holding the bus's
name from the config (`can:` entry `name`, default its channel): every frame this driver
returns names the bus to send it on, and every frame it receives must name the bus it
came on (daemon.service.bus_port.MultiBusPort tags them), so a frame for node 3 on one
bus is never taken for node 3 on another.  Each bus's driver opens its own cycles: one
SYNC per bus.

Start, enable and reset run on every bus at once, as the buses are independent: so an
enable ends on all buses together, and no bus's drives wait in torque mode, unfed,
while another bus enables (an ODrive's watchdog would fire).  The first failure stops
the others and is raised naming its bus.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass

import can

from drivers.base import ActuatorDriver, BrakeMode, DriverError, FrameCounters, FrameError, Link


@dataclass(frozen=True)
class BusDrives:
    """The drives of one bus: its name, the cables they drive (in the driver's order) and
    the protocol driver of those drives."""

    name: str
    cables: list[int]
    driver: ActuatorDriver


class BusLink:
    """One bus of a Link that serves several: frames sent are tagged with the bus's name,
    and only frames that came on it can answer."""

    def __init__(self, link: Link, name: str) -> None:
        self.link = link
        self.name = name

    def send(self, message: can.Message) -> None:
        message.channel = self.name
        self.link.send(message)

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        name = self.name
        return await self.link.expect(lambda msg: msg.channel == name and match(msg), timeout, what)


class MultiBusDriver(ActuatorDriver):
    """The drives of several buses (`parts`, each cable on exactly one) as one driver.
    `feedback[i]` and `status[i]` are the objects of cable i's bus driver."""

    def __init__(self, parts: Sequence[BusDrives], nodes: Sequence[int]) -> None:
        home = {i: (part, j) for part in parts for j, i in enumerate(part.cables)}
        if sorted(home) != list(range(len(home))) or len(home) != len(nodes):
            raise ValueError(f"the buses' drives must cover cables 0..{len(nodes) - 1} once")
        self.parts = list(parts)
        self.timing = parts[0].driver.timing
        self.n = len(home)
        self.nodes = list(nodes)
        at = [home[i] for i in range(self.n)]
        self.scalings = [part.driver.scalings[j] for part, j in at]
        self.feedback = [part.driver.feedback[j] for part, j in at]
        self.status = [part.driver.status[j] for part, j in at]
        self._bus = [part.name for part, _ in at]
        self._by_name = {part.name: part for part in parts}

    @property
    def bus_names(self) -> list[str]:
        return [part.name for part in self.parts]

    @property
    def counters(self) -> FrameCounters:  # type: ignore[override]
        """Every bus driver's frame counters, summed."""
        total = FrameCounters()
        for part in self.parts:
            total.accepted += part.driver.counters.accepted
            total.rejected.update(part.driver.counters.rejected)
        return total

    # -- sequences: on every bus at once ---------------------------------------------------

    async def start(self, link: Link, now: Callable[[], float]) -> None:
        await self._on_every_bus(link, lambda part, bus: part.driver.start(bus, now))

    async def enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
        await self._on_every_bus(
            link,
            lambda part, bus: part.driver.enable(
                bus, [lengths[i] for i in part.cables], [forces[i] for i in part.cables]
            ),
        )

    async def reset_faults(self, link: Link) -> None:
        await self._on_every_bus(link, lambda part, bus: part.driver.reset_faults(bus))

    @property
    def measures_force(self) -> bool:
        return all(part.driver.measures_force for part in self.parts)

    async def measured_forces(self, link: Link) -> list[float]:
        forces: list[float] = [0.0] * self.n

        async def read(part: BusDrives, bus: BusLink) -> None:
            measured = await part.driver.measured_forces(bus)
            for i, force in zip(part.cables, measured, strict=True):
                forces[i] = force

        await self._on_every_bus(link, read)
        return forces

    async def _on_every_bus(
        self, link: Link, step: Callable[[BusDrives, BusLink], Awaitable[None]]
    ) -> None:
        """`step` for every bus's drives concurrently; the first DriverError cancels the
        others and is raised naming its bus."""

        async def on(part: BusDrives) -> None:
            try:
                await step(part, BusLink(link, part.name))
            except DriverError as exc:
                raise DriverError(f"bus {part.name}: {exc}") from exc

        tasks = [asyncio.ensure_future(on(part)) for part in self.parts]
        try:
            await asyncio.gather(*tasks)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    # -- immediate frames ----------------------------------------------------------------

    def cycle_start(self) -> list[can.Message]:
        return self._each(lambda part: part.driver.cycle_start())

    def commands(self, forces: Sequence[float]) -> list[can.Message]:
        if len(forces) != self.n:
            raise FrameError(f"{len(forces)} forces for {self.n} drives")
        for i, force in enumerate(forces):
            if not math.isfinite(force):
                raise FrameError(
                    f"force {force} for cable {i} (node {self.nodes[i]} on bus {self._bus[i]}) "
                    "is not finite"
                )
        return self._each(lambda part: part.driver.commands([forces[i] for i in part.cables]))

    def brake(self, lengths: Sequence[float], mode: BrakeMode) -> list[can.Message]:
        return self._each(
            lambda part: part.driver.brake(
                [lengths[i] if i < len(lengths) else math.nan for i in part.cables], mode
            )
        )

    def disable(self) -> list[can.Message]:
        return self._each(lambda part: part.driver.disable())

    def keepalive(self) -> list[can.Message]:
        return self._each(lambda part: part.driver.keepalive())

    def _each(self, frames_of: Callable[[BusDrives], list[can.Message]]) -> list[can.Message]:
        """The frames of every bus's driver, each tagged with its bus."""
        out: list[can.Message] = []
        for part in self.parts:
            frames = frames_of(part)
            for msg in frames:
                msg.channel = part.name
            out.extend(frames)
        return out

    # -- input ---------------------------------------------------------------------------

    def receive_ids(self) -> frozenset[int]:
        return frozenset().union(*(part.driver.receive_ids() for part in self.parts))

    def receive_ids_on(self, name: str) -> frozenset[int]:
        """The ids read on bus `name` (KeyError if no drive is on it)."""
        return self._by_name[name].driver.receive_ids()

    def receive(self, message: can.Message, now: float) -> int | None:
        """Decoded by the driver of the bus the frame came on (its `channel`); a frame
        naming no bus of this driver is not one of its drives' frames."""
        part = self._by_name.get(message.channel)  # type: ignore[arg-type]
        if part is None:
            return None
        j = part.driver.receive(message, now)
        return None if j is None else part.cables[j]
