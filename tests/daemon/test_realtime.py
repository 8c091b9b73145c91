"""enter_realtime: SCHED_FIFO, affinity and locked memory where permitted, restored after;
where not, normal service and a warning that names what failed and what to allow."""

from __future__ import annotations

import ast
import contextlib
import errno
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon.config import MAX_CPUS, RealtimeConfig
from daemon.process import realtime as rt
from daemon.process.realtime import enter_realtime, leave_realtime, realtime
from tests.processes import ROOT

FIFO = os.SCHED_FIFO
CAP_SYS_RESOURCE = 24


def _policy() -> int:
    return os.sched_getscheduler(0)


def _locked_kb() -> int:
    status = Path("/proc/self/status").read_text()
    return int(status.split("VmLck:")[1].split()[0])


def _privileged() -> bool:
    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= 10


@pytest.fixture(autouse=True)
def normal_afterwards() -> Iterator[None]:
    """Whatever a test does, this process leaves it at normal priority on every CPU,
    with nothing locked."""
    cpus = os.sched_getaffinity(0)
    try:
        yield
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.sched_setaffinity(0, cpus)
        rt._libc().munlockall()


@pytest.mark.skipif(not _privileged(), reason="needs root or RLIMIT_RTPRIO >= 10")
def test_takes_effect_and_is_restored() -> None:
    last = max(os.sched_getaffinity(0))
    before = os.sched_getaffinity(0)
    with realtime(
        RealtimeConfig(priority=10, cpus=(last,), lock_memory=True, cpu_latency_us=None)
    ) as state:
        assert state.warnings == []
        assert (_policy(), os.sched_getparam(0).sched_priority) == (FIFO, 10)
        assert os.sched_getaffinity(0) == {last} == state.cpus
        assert state.memory_locked and _locked_kb() > 0
    assert _policy() == os.SCHED_OTHER and os.sched_getparam(0).sched_priority == 0
    assert os.sched_getaffinity(0) == before
    assert _locked_kb() == 0


def test_the_gil_is_handed_back_within_a_fraction_of_a_period() -> None:
    """Unprivileged too: the switch interval is the core's whatever the scheduling (a
    thread holding the GIL kept a cycle waiting for up to Python's 5 ms), and is
    Python's again after."""
    before = sys.getswitchinterval()
    with realtime(RealtimeConfig()):
        assert sys.getswitchinterval() == pytest.approx(rt.GIL_SWITCH_INTERVAL)
        assert rt.GIL_SWITCH_INTERVAL <= 0.25 * (1.0 / 1000.0)  # a quarter period at 1 kHz
    assert sys.getswitchinterval() == before


@pytest.mark.skipif(not _privileged(), reason="needs root or RLIMIT_RTPRIO >= 10")
def test_a_thread_started_afterwards_inherits_priority_and_cpus() -> None:
    """A thread the cycle waits on (a python-can Notifier) must run at the core's
    priority: SCHED_RESET_ON_FORK would start it at normal priority."""
    seen: list[tuple[int, int, set[int]]] = []

    def look() -> None:
        seen.append((_policy(), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0)))

    last = max(os.sched_getaffinity(0))
    with realtime(
        RealtimeConfig(priority=10, cpus=(last,), lock_memory=False, cpu_latency_us=None)
    ) as state:
        assert state.priority == 10
        thread = threading.Thread(target=look)
        thread.start()
        thread.join(timeout=30)
    assert seen == [(FIFO, 10, {last})]


REPORT = (
    "import os, sys; fd = int(sys.argv[1]); "
    "os.write(fd, repr((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, "
    "sorted(os.sched_getaffinity(0)), sys.argv[2], os.environ['MARK'])).encode())"
)


def _spawned_sees(cpus: tuple[int, ...] | None) -> tuple:
    """What a child of spawn_ordinary sees (policy, priority, CPUs, argument, env),
    spawned from here under realtime(priority 10, `cpus`)."""
    read, write = os.pipe()
    try:
        with realtime(
            RealtimeConfig(priority=10, cpus=cpus, lock_memory=False, cpu_latency_us=None)
        ):
            argv = [sys.executable, "-c", REPORT, str(write), "an argument"]
            child = rt.spawn_ordinary(argv, {**os.environ, "MARK": "env"}, (write,))
        os.close(write)
        with os.fdopen(read) as report:
            seen = report.read()  # until the child exits
        os.waitpid(child.pid, 0)
        return ast.literal_eval(seen)
    finally:
        with contextlib.suppress(OSError):
            os.close(write)


@pytest.mark.skipif(not _privileged(), reason="needs root or RLIMIT_RTPRIO >= 10")
def test_a_process_the_core_starts_runs_at_normal_priority_on_every_cpu() -> None:
    """The companion and the demo's client must never compete with the cycle: spawned
    from a core pinned to one CPU, the child runs at SCHED_OTHER on every CPU, with its
    arguments, environment and passed descriptor."""
    every = sorted(os.sched_getaffinity(0))
    seen = _spawned_sees((max(every),))
    assert seen == (os.SCHED_OTHER, 0, every, "an argument", "env")


@pytest.mark.skipif(not _privileged(), reason="needs root or RLIMIT_RTPRIO >= 10")
def test_a_real_time_caller_spawns_above_normal_processes_until_the_exec(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """posix_spawn holds the caller until the child execs: from the core, the child
    starts at SCHED_FIFO 1 (ahead of every normal process, behind the cycle) and execs
    the trampoline that drops it to normal (daemon.process.ordinary); a caller at
    normal priority spawns at SCHED_OTHER directly."""
    calls: list[tuple[list[str], tuple]] = []

    def spawn(path: str, argv: list[str], env: dict, **options: object) -> int:
        calls.append((argv, options["scheduler"]))
        return os.getpid()

    monkeypatch.setattr(os, "posix_spawn", spawn)
    with realtime(RealtimeConfig(priority=10, cpus=None, lock_memory=False, cpu_latency_us=None)):
        rt.spawn_ordinary(["/bin/true", "x"], {})
    rt.spawn_ordinary(["/bin/true", "y"], {})
    (fifo_argv, fifo), (other_argv, other) = calls
    assert fifo == (FIFO, os.sched_param(1))
    assert fifo_argv == [sys.executable, "-I", "-S", rt.ORDINARY, "/bin/true", "x"]
    assert other == (os.SCHED_OTHER, os.sched_param(0)) and other_argv == ["/bin/true", "y"]


def test_the_trampoline_names_a_program_it_cannot_run() -> None:
    done = subprocess.run(
        [sys.executable, "-I", "-S", rt.ORDINARY, "/nonexistent/program", "arg"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 127
    assert done.stderr == "error: cannot run /nonexistent/program: No such file or directory\n"


def test_refused_priority_keeps_normal_scheduling_and_says_what_to_allow(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(*_args: object) -> None:
        raise PermissionError(errno.EPERM, os.strerror(errno.EPERM))

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.INFO, logger="cdprd"):
        state = enter_realtime(RealtimeConfig(priority=50, lock_memory=False, cpu_latency_us=None))
    assert state.priority == 0 and _policy() == os.SCHED_OTHER
    (warning,) = state.warnings
    assert warning.startswith("SCHED_FIFO priority 50 refused (Operation not permitted)")
    for remedy in ("LimitRTPRIO=50", "RestrictRealtime=no", "ulimit -r 50", "CAP_SYS_NICE"):
        assert remedy in warning
    assert "realtime.priority: 0" in warning
    logged = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage() for r in logged] == [f"real-time: {warning}"]
    assert "normal priority" in caplog.records[-1].getMessage()


def test_failed_mlockall_is_a_warning_naming_the_memlock_limit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(rt, "_mlockall", lambda flags: errno.ENOMEM)
    monkeypatch.setattr(rt, "_has_capability", lambda bit: True)
    state = enter_realtime(RealtimeConfig(priority=0, lock_memory=True, cpu_latency_us=None))
    assert not state.memory_locked
    (warning,) = state.warnings
    assert warning.startswith("memory not locked: mlockall failed (Cannot allocate memory;")
    assert "RLIMIT_MEMLOCK" in warning and "LimitMEMLOCK=infinity" in warning


def test_nothing_is_asked_when_not_configured(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*_args: object) -> None:
        raise AssertionError("asked the kernel for something not configured")

    for name in ("sched_setscheduler", "sched_setaffinity"):
        monkeypatch.setattr(os, name, forbidden)
    monkeypatch.setattr(rt, "_mlockall", forbidden)
    monkeypatch.setattr(rt, "_hold_cpu_latency", forbidden)
    for priority in (0, None):
        state = enter_realtime(
            RealtimeConfig(priority=priority, cpus=None, lock_memory=False, cpu_latency_us=None)
        )
        assert (state.priority, state.memory_locked, state.warnings) == (0, False, [])
        leave_realtime(state)


def test_cpus_the_kernel_cannot_use_are_named() -> None:
    absent = MAX_CPUS - 1  # no machine here has that many
    before = frozenset(os.sched_getaffinity(0))
    first = min(before)
    state = enter_realtime(
        RealtimeConfig(priority=0, cpus=(first, absent), lock_memory=False, cpu_latency_us=None)
    )
    try:
        assert state.cpus == {first} and os.sched_getaffinity(0) == {first}
        (warning,) = state.warnings
        assert warning.startswith(f"realtime.cpus: CPU {absent} cannot be used")
        assert f"the core runs on CPU {first}" in warning
    finally:
        leave_realtime(state)
    assert os.sched_getaffinity(0) == before
    state = enter_realtime(
        RealtimeConfig(priority=0, cpus=(absent,), lock_memory=False, cpu_latency_us=None)
    )
    assert state.cpus == before == os.sched_getaffinity(0)
    (warning,) = state.warnings
    assert warning.startswith(f"realtime.cpus: none of CPU {absent} can be used")


def test_the_throttling_bound_is_reported_and_its_absence_warned(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(os, "sched_setscheduler", lambda *_args: None)  # granted, no effect
    state = enter_realtime(RealtimeConfig(priority=50, lock_memory=False, cpu_latency_us=None))
    expected = int((rt.PROC_SYS_KERNEL / "sched_rt_runtime_us").read_text())
    assert state.rt_runtime_us == expected
    assert f"real-time throttling {expected}/" in rt.describe(state)
    (tmp_path / "sched_rt_runtime_us").write_text("-1\n")
    (tmp_path / "sched_rt_period_us").write_text("1000000\n")
    monkeypatch.setattr(rt, "PROC_SYS_KERNEL", tmp_path)
    state = enter_realtime(RealtimeConfig(priority=50, lock_memory=False, cpu_latency_us=None))
    (warning,) = state.warnings
    assert warning.startswith("kernel real-time throttling is off (sched_rt_runtime_us = -1)")
    assert "real-time throttling off" in rt.describe(state)


# -- the same in a process with the permissions config/cdprd.service gives ---------------------

CHILD = """
import json, os
from daemon.config import MAX_CPUS, RealtimeConfig
from daemon.process.realtime import enter_realtime
state = enter_realtime(RealtimeConfig(priority=50, lock_memory=True))
print(json.dumps({"priority": state.priority, "locked": state.memory_locked,
                  "warnings": state.warnings, "policy": os.sched_getscheduler(0)}))
"""


def _without_capabilities(rtprio: int, memlock: int) -> dict:
    """enter_realtime in a child with no capability at all (CapabilityBoundingSet= empty)
    and the given RLIMIT_RTPRIO and RLIMIT_MEMLOCK, as the unit's Limit*= set them."""
    setpriv = shutil.which("setpriv")
    if setpriv is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv (util-linux) to drop every capability")
    for limit, value in ((resource.RLIMIT_RTPRIO, rtprio), (resource.RLIMIT_MEMLOCK, memlock)):
        hard = resource.getrlimit(limit)[1]
        raises = hard != resource.RLIM_INFINITY and not 0 <= value <= hard
        if raises and not rt._has_capability(CAP_SYS_RESOURCE):
            pytest.skip(f"raising a hard limit to {value} needs CAP_SYS_RESOURCE, absent here")

    def limits() -> None:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (rtprio, rtprio))
        resource.setrlimit(resource.RLIMIT_MEMLOCK, (memlock, memlock))

    command = [setpriv, "--bounding-set=-all", "--no-new-privs", sys.executable, "-c", CHILD]
    child = subprocess.run(
        command, cwd=ROOT, preexec_fn=limits, capture_output=True, text=True, timeout=60
    )
    assert child.returncode == 0, child.stderr[-2000:]
    return json.loads(child.stdout)


def test_the_units_limits_suffice_without_any_capability() -> None:
    got = _without_capabilities(rtprio=50, memlock=resource.RLIM_INFINITY)
    assert got["warnings"] == []
    assert (got["priority"], got["locked"]) == (50, True)
    assert got["policy"] == FIFO


def test_without_the_units_limits_the_core_runs_on_with_two_warnings() -> None:
    got = _without_capabilities(rtprio=0, memlock=8 << 20)
    assert (got["priority"], got["locked"], got["policy"]) == (0, False, os.SCHED_OTHER)
    memory, fifo = got["warnings"]
    assert memory.startswith(f"memory not locked: RLIMIT_MEMLOCK is {8 << 20} bytes")
    assert "LimitMEMLOCK=infinity" in memory
    assert fifo.startswith("SCHED_FIFO priority 50 refused (Operation not permitted)")
    assert "RLIMIT_RTPRIO, now 0" in fifo


# -- the CPU latency ------------------------------------------------------------------------


def _cpu_latency_now() -> int:
    """The kernel's CPU latency target in force (us): the least any open request holds
    (a read of /dev/cpu_dma_latency gives it; this file's own request asks nothing)."""
    reader = os.open(rt.CPU_LATENCY, os.O_RDONLY)
    try:
        return int.from_bytes(os.read(reader, 4), sys.byteorder, signed=True)
    finally:
        os.close(reader)


@pytest.mark.skipif(
    not os.access(rt.CPU_LATENCY, os.W_OK), reason=f"needs write access to {rt.CPU_LATENCY}"
)
@pytest.mark.parametrize("us", [0, 20])
def test_the_cpu_latency_is_held_while_in_real_time_and_let_go_after(us: int) -> None:
    """The request stands while the file is open (another process holding a lower one,
    a daemon test beside this one, lowers the target further, never raises it) and is
    let go by leave_realtime; it is no descriptor a child would inherit."""
    with realtime(RealtimeConfig(priority=0, lock_memory=False, cpu_latency_us=us)) as state:
        held = state.cpu_latency_file
        assert held is not None and state.cpu_latency_us == us and state.warnings == []
        assert os.readlink(f"/proc/self/fd/{held}") == str(rt.CPU_LATENCY)
        assert 0 <= _cpu_latency_now() <= us
        assert not os.get_inheritable(held)
        assert rt.describe(state).endswith(f"CPU latency held at {us} us")
    assert state.cpu_latency_file is None and state.cpu_latency_us is None
    try:  # closed, so the kernel dropped the request (its number may be another file's)
        now_open = os.readlink(f"/proc/self/fd/{held}")
    except FileNotFoundError:
        now_open = None
    assert now_open != str(rt.CPU_LATENCY)


def test_an_unopenable_cpu_latency_is_a_warning_naming_what_to_allow(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(rt, "CPU_LATENCY", tmp_path / "cpu_dma_latency")
    state = enter_realtime(RealtimeConfig(priority=0, lock_memory=False, cpu_latency_us=0))
    assert state.cpu_latency_file is None and state.cpu_latency_us is None
    (warning,) = state.warnings
    assert warning.startswith(
        f"CPU latency 0 us not held: {tmp_path / 'cpu_dma_latency'}: No such file or directory"
    )
    for remedy in (rt.CPU_LATENCY_RULE, "DeviceAllow=", "realtime.cpu_latency_us: null"):
        assert remedy in warning
    assert rt.describe(state).endswith("CPU idle states as they are")
    leave_realtime(state)


def test_a_refused_cpu_latency_write_is_a_warning_and_leaves_nothing_open(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """/dev/full takes the open and refuses every write (ENOSPC)."""
    monkeypatch.setattr(rt, "CPU_LATENCY", Path("/dev/full"))
    before = set(os.listdir("/proc/self/fd"))
    state = enter_realtime(RealtimeConfig(priority=0, lock_memory=False, cpu_latency_us=5))
    assert state.cpu_latency_file is None
    (warning,) = state.warnings
    assert warning == "CPU latency 5 us not held: /dev/full refused it: No space left on device"
    assert set(os.listdir("/proc/self/fd")) == before


def test_the_unit_lets_the_core_hold_the_cpu_latency_the_udev_rule_opens() -> None:
    """The node the core opens is the one config/cdprd.service allows and the udev rule
    shipped beside it makes writable for the unit's dynamic user."""
    unit = (ROOT / rt.UNIT).read_text()
    assert f"\nDeviceAllow={rt.CPU_LATENCY} w\n" in unit
    assert "\nDevicePolicy=closed\n" in unit and "\nPrivateDevices=no\n" in unit
    rules = [
        line
        for line in (ROOT / rt.CPU_LATENCY_RULE).read_text().splitlines()
        if line and not line.startswith("#")
    ]
    assert rules == [f'KERNEL=="{rt.CPU_LATENCY.name}", MODE="0666"']
