"""The simulator's clock against the frames: a drive latches on a SYNC at the instant the
SYNC was sent (its stamp), between plant steps and also when this process was held up
before the simulator read it, as a real drive on its own processor does."""

from __future__ import annotations

import asyncio
import math
import time
from types import SimpleNamespace

import can
import numpy as np
import pytest

from daemon.cli.simulated import InProcessSimulator
from drivers.cia402.codec import SYNC_ID
from sim_bus.__main__ import failure_note
from sim_bus.plant.config import EncoderConfig
from sim_bus.plant.encoder import Encoders
from tests.daemon_stack import config_for


def test_a_reading_between_steps_is_carried_on_at_the_last_steps_rate() -> None:
    encoders = Encoders(
        EncoderConfig(counts_per_metre=None), 2, step=1e-3, rng=np.random.default_rng(0)
    )
    encoders.reset([1.0, 2.0], [0.5, -1.0])
    lengths, rates = encoders.read()
    assert lengths.tolist() == [1.0, 2.0]
    ahead, ahead_rates = encoders.read(0.4e-3)
    assert ahead == pytest.approx([1.0 + 0.5 * 0.4e-3, 2.0 - 1.0 * 0.4e-3], abs=1e-12)
    assert ahead_rates == pytest.approx(rates, abs=1e-9)


def test_a_sync_read_late_is_taken_at_the_moment_it_was_sent() -> None:
    """The loop is held up 50 ms between the SYNC's send and the simulator's read: the
    drives take it at its stamp, not 50 ms later."""

    async def scenario() -> tuple[float, list[float]]:
        sim = InProcessSimulator(config_for("cia402"))
        taken: list[float] = []
        handle = sim.robot.handle

        def spy(message: can.Message, t: float) -> list[can.Message]:
            if message.arbitration_id == SYNC_ID:
                taken.append(t)
            return handle(message, t)

        sim.robot.handle = spy  # type: ignore[method-assign]
        sim.start()
        try:
            await asyncio.sleep(0.02)
            sent = sim.runner.t
            sim.daemon_bus.send(can.Message(arbitration_id=SYNC_ID, is_extended_id=False))
            time.sleep(0.05)  # this process held up: the simulator reads the SYNC late
            await asyncio.sleep(0.02)
            return sent, taken
        finally:
            sim.close()

    sent, taken = asyncio.run(scenario())
    assert len(taken) == 1
    assert taken[0] == pytest.approx(sent, abs=0.01)  # read at sent + 0.05 or later


def test_syncs_answered_after_the_hosts_deadline_are_counted_and_the_slowest_kept() -> None:
    """The loop held up 0.2 s after a SYNC went out: its answers leave that late, past a
    0.1 s deadline (a deadline miss the simulator's process caused); a SYNC read at once
    is answered in time.  take_answers gives each window's figures once."""

    async def scenario() -> list[tuple[float, int]]:
        sim = InProcessSimulator(config_for("cia402"))
        sim.runner.answer_deadline = 0.1
        sim.start()
        windows = []
        try:
            await asyncio.sleep(0.02)
            sim.runner.take_answers()
            sync = can.Message(arbitration_id=SYNC_ID, is_extended_id=False)
            sim.daemon_bus.send(sync)
            time.sleep(0.2)  # this process held up: the SYNC waits to be read
            await asyncio.sleep(0.02)
            windows.append(sim.runner.take_answers())
            sim.daemon_bus.send(sync)
            await asyncio.sleep(0.02)
            windows.append(sim.runner.take_answers())
            windows.append(sim.runner.take_answers())
            return windows
        finally:
            sim.close()

    (held, held_late), (prompt, prompt_late), (none, none_late) = asyncio.run(scenario())
    assert held >= 0.2 and held_late == 1
    assert 0.0 < prompt < 0.1 and prompt_late == 0
    assert none == 0.0 and none_late == 0


@pytest.mark.parametrize("own_process", [True, False])
def test_a_wake_up_the_host_held_up_is_measured_and_logged_in_a_process_of_its_own(
    own_process: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """The loop held up 60 ms: the next wake-up comes that late, which the runner gives
    the truth log once (take_latest_wake_up) and, in a process of its own, logs (in
    process the daemon's own work holds the loop up, and the daemon reports that)."""
    from sim_bus.bus.loopbus import LoopBus
    from sim_bus.runner import HELD_UP, SimulatorRunner

    async def scenario() -> tuple[float, float]:
        sim = InProcessSimulator(config_for("cia402"))
        bus = LoopBus(channel="cdprd-held-up-test")
        runner = SimulatorRunner(sim.robot, bus, own_process=own_process)
        runner.start()
        try:
            await asyncio.sleep(0.05)
            runner.take_latest_wake_up()
            time.sleep(0.06)  # this process held up
            await asyncio.sleep(0.01)
            return runner.take_latest_wake_up(), runner.take_latest_wake_up()
        finally:
            runner.close()
            bus.shutdown()
            sim.close()

    with caplog.at_level("WARNING", logger="sim_bus.runner"):
        latest, again = asyncio.run(scenario())
    assert latest >= 0.055 and latest >= HELD_UP
    assert again < latest  # taken: the next read starts afresh
    late = [m for r in caplog.records if "(held up: its drives" in (m := r.getMessage())]
    if own_process:
        assert late and max(float(m.split()[2]) for m in late) >= 55.0, late
    else:
        assert not late


@pytest.mark.parametrize(("protocol", "sync"), [("cia402", True), ("odrive", False)])
def test_only_cia402_drives_take_id_0x080_for_a_sync(protocol: str, sync: bool) -> None:
    """To ODrives a standard 0x080 frame is node 4's command 0, never a SYNC to latch on
    or to rephase the clock by; an extended 0x080 is a SYNC to no one."""
    sim = InProcessSimulator(config_for(protocol))
    try:
        robot = sim.robot
        assert robot.is_sync(can.Message(arbitration_id=SYNC_ID, is_extended_id=False)) is sync
        assert not robot.is_sync(can.Message(arbitration_id=SYNC_ID, is_extended_id=True))
    finally:
        sim.close()


def test_the_status_line_names_failed_sends_and_receives_only_when_there_are_some() -> None:
    runner = SimpleNamespace(send_errors=0, receive_errors=0)
    assert failure_note(runner) == ""
    runner.send_errors, runner.receive_errors = 3, 1
    assert failure_note(runner) == "; 3 sends failed, 1 receives failed"


def test_the_simulator_process_collects_garbage_between_frames_as_the_core_does() -> None:
    """With a collector (python -m sim_bus passes one) the runner freezes the start-up
    heap and turns automatic collection off while it runs (without it: a full collection
    of 45 ms as it started serving, young ones of up to 1 ms), collects young garbage after
    the answers went out, and gives collection back when closed."""
    import gc

    from drivers.gc_policy import CollectorPolicy
    from sim_bus.bus.loopbus import LoopBus
    from sim_bus.runner import SimulatorRunner

    async def scenario() -> tuple[bool, int, int]:
        sim = InProcessSimulator(config_for("cia402"))
        bus = LoopBus(channel="cdprd-gc-test")
        collector = CollectorPolicy()
        runner = SimulatorRunner(sim.robot, bus, collector=collector)
        runner.start()
        try:
            running = gc.isenabled()
            frozen = gc.get_freeze_count()
            young, _, _ = gc.get_threshold()
            for _ in range(young + 1):  # garbage in cycles: only a collection frees it
                cycle: list = []
                cycle.append(cycle)
            runner._handle([], runner.lanes[None])  # the answers (none) went out
            return running, frozen, collector.stats.young
        finally:
            runner.close()
            bus.shutdown()
            sim.close()

    running, frozen, collections = asyncio.run(scenario())
    assert not running and frozen > 0
    assert collections >= 1
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_syncs_next_to_the_plants_steps_hold_the_clock_back_so_they_come_half_a_step_in() -> None:
    """SYNCs stamped just after the simulator's step boundaries (where the wake-up that
    steps the plant is in their way): after REPHASE_AFTER of them, every cable at rest,
    the clock is held back by less than a step (never forward) so that they come half a
    step in; SYNCs there leave it alone; while a cable moves it is never moved."""
    from sim_bus.bus.loopbus import LoopBus
    from sim_bus.runner import REPHASE_AFTER, SimulatorRunner

    async def scenario() -> list[float]:
        sim = InProcessSimulator(config_for("cia402"))
        bus = LoopBus(channel="cdprd-phase-test")
        runner = SimulatorRunner(sim.robot, bus)
        runner.start()
        step = sim.robot.plant.config.step
        epochs = []  # the simulator's time 0 on this host's clock, after each SYNC

        def syncs(phase: float) -> None:
            first = (math.floor(runner.t / step) - 2 * REPHASE_AFTER) * step
            for k in range(REPHASE_AFTER):
                at = first + (k + phase) * step  # in the past: a SYNC read late
                stamp = time.time() - time.monotonic() + runner.monotonic(at)
                sync = can.Message(arbitration_id=SYNC_ID, is_extended_id=False, timestamp=stamp)
                runner._handle([sync], runner.lanes[None])
                epochs.append(runner.monotonic(0.0))

        try:
            assert all(drive.rate == 0.0 for drive in sim.robot.drives)
            syncs(0.05)  # just after a boundary: held back 0.55 step at the last
            syncs(0.5)
            syncs(0.9)  # just before one: held back 0.4 step
            sim.robot.drives[3].rate = 0.01  # a cable moves
            syncs(0.1)
            assert runner._timer is not None  # it wakes on the new steps' boundaries:
            woken = (runner._timer.start - runner.monotonic(0.0)) / step
            assert woken == pytest.approx(round(woken), abs=1e-6)
            return [e / step for e in epochs]
        finally:
            runner.close()
            bus.shutdown()
            sim.close()

    # a stamp goes between the wall and monotonic clocks, read a moment apart: within
    # 0.05 step (the phases above are 0.15 step or more from the tolerance's edges)
    epochs = np.array(asyncio.run(scenario()))
    moves = np.diff(epochs)
    n = REPHASE_AFTER
    assert moves[n - 2] == pytest.approx(0.55, abs=0.05)
    assert moves[3 * n - 2] == pytest.approx(0.4, abs=0.05)
    others = np.delete(moves, [n - 2, 3 * n - 2])
    assert np.abs(others).max() < 0.05
