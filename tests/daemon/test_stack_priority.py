"""The in-process stack (tests/daemon_stack.Stack) on a host that gives real-time work
less of a CPU than the stack needs: it must hold, not brake.

The core and the simulator share one thread in the stack.  At SCHED_FIFO the kernel's
real-time throttling stopped that thread for up to 50 ms a second once it used more
than its budget, and the drives' heartbeat consumers braked the robot (EMCY 0x8130): the
CI's signature, reproduced here by a cgroup whose real-time budget is 60 % of each
second.  The stack runs at nice -20 instead, which no real-time budget limits."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CPU_CGROUP = Path("/sys/fs/cgroup/cpu")  # cgroup v1's cpu controller, with RT group time
BUDGET_US = 600_000  # of each 1,000,000 us

HOLD = textwrap.dedent(
    """
    import asyncio
    from daemon.service.safety import SafetyState
    from tests.daemon_stack import Stack, config_for

    async def main():
        async with Stack(config_for("cia402")) as stack:
            await stack.enable()
            await asyncio.sleep(3.0)
            machine = stack.service.machine
            print(machine.state.value, machine.fault)
            assert machine.state is SafetyState.HOLD, machine.fault

    asyncio.run(main())
    """
)


def _limited_cgroup() -> Path:
    """A child cpu cgroup with a 60 % real-time budget, or skip saying why there is none."""
    if not (CPU_CGROUP / "cpu.rt_runtime_us").exists():
        pytest.skip("no cgroup v1 cpu controller with real-time group scheduling here")
    group = CPU_CGROUP / f"cdprd-test-{os.getpid()}"
    try:
        group.mkdir(exist_ok=True)
        (group / "cpu.rt_runtime_us").write_text(f"{BUDGET_US}\n")
    except OSError as exc:
        pytest.skip(f"cannot make a cgroup with a real-time budget here: {exc}")
    return group


@pytest.mark.slow
def test_the_stack_holds_where_real_time_work_gets_60_percent_of_a_cpu() -> None:
    group = _limited_cgroup()
    enter = f'echo $$ > {group / "cgroup.procs"} && exec {sys.executable} -c "$0"'
    try:
        done = subprocess.run(
            ["sh", "-c", enter, HOLD], cwd=ROOT, capture_output=True, text=True, timeout=120
        )
    finally:
        group.rmdir()  # empty again: its one process has exited
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split()[0] == "hold", done.stdout
