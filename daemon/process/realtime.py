"""Real-time service for the core process: SCHED_FIFO, CPU affinity, locked memory, CPUs
kept awake.

The process that runs the control cycle calls `enter_realtime(config.realtime)` once at
start-up, from the thread that runs the cycle: the kernel applies scheduling policy and
affinity per thread, and what that thread starts afterwards inherits them, threads (a
python-can Notifier thread the cycle waits on, say) and child processes alike.  So start
the companion process before, or have it return to normal scheduling first thing.  Each
request that is not permitted leaves that part as it was and adds a warning that names
what failed and what to allow; the core then runs on without it.

- SCHED_FIFO at `priority`.  Not SCHED_RESET_ON_FORK: the kernel would then start every
  thread the core starts at normal priority, a thread the cycle waits on included.
- Affinity to `cpus`; CPUs the kernel does not grant are named (absent, offline, or
  outside the service's cpuset).
- mlockall(MCL_CURRENT | MCL_FUTURE): every page now and every later one resident, so no
  cycle waits for a page fault or a page-in.  With MCL_FUTURE an allocation past
  RLIMIT_MEMLOCK fails (MemoryError), so without CAP_IPC_LOCK memory is locked only when
  that limit is unlimited.
- The CPU latency QoS at `cpu_latency_us` (/dev/cpu_dma_latency, held open while the core
  runs, as cyclictest does): at 0 an idle CPU stays in its shallowest idle state (x86's
  cpuidle polls; an ARM CPU waits in WFI) instead of one that is slow to leave, so no
  wake-up of the cycle waits for one; the idle CPUs spend power instead.
  docs/explanation/realtime.md has its figures on this project's host, a VM, where it
  also has a cost.
- The GIL's switch interval: GIL_SWITCH_INTERVAL instead of Python's 5 ms, so that
  another Python thread of the core's process (zenoh's callbacks, a Notifier thread)
  holding the GIL gives it back to the cycle within a fraction of a period.  With 5 ms,
  a cycle woken by its timer could wait that long for the GIL: `cdprd demo` flew at
  0.23-1.07 mm RMS with 140 overruns, and at 0.09-0.10 mm with 0.2 ms.
- Garbage collection is not done here: the service's CollectorPolicy
  (drivers/gc_policy.py) collects before the first cycle, then freezes the
  start-up heap and turns automatic collection off.

A cycle that never ends at SCHED_FIFO would keep everything else off its CPUs.  The
kernel's real-time throttling bounds that: real-time threads get at most
sched_rt_runtime_us of every sched_rt_period_us (default 950000 of 1000000) per CPU.
`enter_realtime` reads the bound and warns when it is off.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import logging
import os
import resource
import signal
import struct
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from daemon.config import RealtimeConfig
from daemon.process import ordinary

log = logging.getLogger("cdprd")

MCL_CURRENT, MCL_FUTURE = 1, 2  # <sys/mman.h>
CAP_IPC_LOCK = 14  # <linux/capability.h>
PROC_SYS_KERNEL = Path("/proc/sys/kernel")
CPUS_ONLINE = Path("/sys/devices/system/cpu/online")
CPU_LATENCY = Path("/dev/cpu_dma_latency")  # the kernel's CPU latency QoS, per open file
CPU_LATENCY_RULE = "config/60-cdprd-cpu-latency.rules"
UNIT = "config/cdprd.service"
ORDINARY = ordinary.__file__  # the trampoline spawn_ordinary runs first
SPAWN_PRIORITY = 1  # SCHED_FIFO priority of a child until it has dropped to normal
GIL_SWITCH_INTERVAL = 2.5e-4  # s: sys.setswitchinterval for the core's process


@dataclass
class RealtimeState:
    """What `enter_realtime` obtained, and what `leave_realtime` restores.

    priority: the SCHED_FIFO priority in force, 0 for normal scheduling.  cpus: the CPUs
    the core may run on now.  memory_locked: mlockall in force.  rt_runtime_us /
    rt_period_us: the kernel's real-time throttling (None if unreadable; runtime -1:
    off).  cpu_latency_us: the CPU latency this process holds (None: none), through the
    open file `cpu_latency_file`.  warnings: each request that was not granted, and why.
    """

    priority: int
    cpus: frozenset[int]
    memory_locked: bool
    rt_runtime_us: int | None
    rt_period_us: int | None
    warnings: list[str] = field(default_factory=list)
    cpu_latency_us: int | None = None
    cpu_latency_file: int | None = None
    previous_policy: int = os.SCHED_OTHER
    previous_priority: int = 0
    previous_cpus: frozenset[int] = frozenset()
    previous_switch_interval: float = 0.005


def enter_realtime(settings: RealtimeConfig) -> RealtimeState:
    """Ask for what `settings` configures (see the module docstring); log what was
    obtained and a warning for each part that was not."""
    previous_cpus = frozenset(os.sched_getaffinity(0))
    warnings: list[str] = []
    cpus = previous_cpus
    if settings.cpus is not None:
        cpus = _set_affinity(frozenset(settings.cpus), previous_cpus, warnings)
    locked = settings.lock_memory and _lock_memory(warnings)
    latency_file = None
    if settings.cpu_latency_us is not None:
        latency_file = _hold_cpu_latency(settings.cpu_latency_us, warnings)
    previous_policy, previous_priority = os.sched_getscheduler(0), os.sched_getparam(0)
    priority = _set_fifo(settings.priority, warnings) if settings.priority else 0
    previous_switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)
    runtime, period = _read_int("sched_rt_runtime_us"), _read_int("sched_rt_period_us")
    if priority and runtime is not None and (runtime < 0 or runtime == period):
        warnings.append(
            f"kernel real-time throttling is off (sched_rt_runtime_us = {runtime}): a core "
            "that never yields would keep every other task off its CPUs; `sysctl "
            "kernel.sched_rt_runtime_us=950000` restores the default bound"
        )
    state = RealtimeState(
        priority=priority,
        cpus=cpus,
        memory_locked=locked,
        rt_runtime_us=runtime,
        rt_period_us=period,
        warnings=warnings,
        previous_policy=previous_policy,
        previous_priority=previous_priority.sched_priority,
        previous_cpus=previous_cpus,
        previous_switch_interval=previous_switch_interval,
        cpu_latency_us=None if latency_file is None else settings.cpu_latency_us,
        cpu_latency_file=latency_file,
    )
    for warning in warnings:
        log.warning("real-time: %s", warning)
    log.info("real-time: %s", describe(state))
    return state


def leave_realtime(state: RealtimeState) -> None:
    """Undo `enter_realtime` in this thread: the scheduling and CPUs it had before,
    memory unlocked, Python's switch interval as it was, the CPU latency let go."""
    sys.setswitchinterval(state.previous_switch_interval)
    if state.cpu_latency_file is not None:
        os.close(state.cpu_latency_file)
        state.cpu_latency_file, state.cpu_latency_us = None, None
    if state.priority:
        os.sched_setscheduler(0, state.previous_policy, os.sched_param(state.previous_priority))
    if state.cpus != state.previous_cpus:
        os.sched_setaffinity(0, state.previous_cpus)
    if state.memory_locked:
        _libc().munlockall()


class Child:
    """A process started by `spawn_ordinary`, polled without blocking."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        """The exit code (-N: killed by signal N) once it has exited, else None."""
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid == self.pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def kill(self) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)


def spawn_ordinary(
    argv: list[str],
    env: dict[str, str],
    pass_fds: tuple[int, ...] = (),
    stdout: int | None = None,
) -> Child:
    """Start `argv` (argv[0] a path) at normal priority on every CPU, without holding up
    the caller for long: posix_spawn (vfork: nothing of the caller's locked memory is
    copied, the caller waits until the child execs).  From a real-time caller the child
    starts at SCHED_FIFO priority 1 and execs the daemon.process.ordinary trampoline at
    once, which drops to normal scheduling and runs `argv` (its docstring says why);
    else it starts at SCHED_OTHER and runs `argv` directly.  Either way its start-up
    (imports take seconds of CPU) never competes with the cycle at the cycle's priority.
    `pass_fds` stay open in the child under the same numbers; `stdout`, if given,
    becomes its stdout."""
    if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        argv = [sys.executable, "-I", "-S", ORDINARY, *argv]
        scheduler = (os.SCHED_FIFO, os.sched_param(SPAWN_PRIORITY))
    else:
        scheduler = (os.SCHED_OTHER, os.sched_param(0))
    for fd in pass_fds:
        os.set_inheritable(fd, True)
    try:
        actions = [] if stdout is None else [(os.POSIX_SPAWN_DUP2, stdout, 1)]
        pid = os.posix_spawn(argv[0], argv, env, file_actions=actions, scheduler=scheduler)
    finally:
        for fd in pass_fds:
            os.set_inheritable(fd, False)
    return Child(pid)


@contextmanager
def realtime(settings: RealtimeConfig) -> Iterator[RealtimeState]:
    """`enter_realtime` for the block, `leave_realtime` after it (tests, benchmarks)."""
    state = enter_realtime(settings)
    try:
        yield state
    finally:
        leave_realtime(state)


def describe(state: RealtimeState) -> str:
    """One line: scheduling, CPUs, memory, throttling, CPU latency."""
    scheduling = f"SCHED_FIFO priority {state.priority}" if state.priority else "normal priority"
    memory = "memory locked" if state.memory_locked else "memory not locked"
    if state.rt_runtime_us is None:
        throttle = "real-time throttling unknown"
    elif state.rt_runtime_us < 0:
        throttle = "real-time throttling off"
    else:
        throttle = f"real-time throttling {state.rt_runtime_us}/{state.rt_period_us} us"
    latency = (
        "CPU idle states as they are"
        if state.cpu_latency_us is None
        else f"CPU latency held at {state.cpu_latency_us} us"
    )
    return f"{scheduling}, CPUs {_cpu_list(state.cpus)}, {memory}, {throttle}, {latency}"


def _set_affinity(
    wanted: frozenset[int], current: frozenset[int], warnings: list[str]
) -> frozenset[int]:
    """The CPUs the kernel grants of `wanted` (it drops those it cannot use), or
    `current` if none."""
    try:
        os.sched_setaffinity(0, wanted)
    except OSError as exc:
        warnings.append(
            f"realtime.cpus: none of CPU {_cpu_list(wanted)} can be used ({exc.strerror}; "
            f"{_online()}): the core stays on CPU {_cpu_list(current)}"
        )
        return current
    granted = frozenset(os.sched_getaffinity(0))
    if granted != wanted:
        warnings.append(
            f"realtime.cpus: CPU {_cpu_list(wanted - granted)} cannot be used (absent, "
            f"offline or outside the service's cpuset; {_online()}): the core runs on CPU "
            f"{_cpu_list(granted)}"
        )
    return granted


def _lock_memory(warnings: list[str]) -> bool:
    """mlockall, if an allocation cannot fail for it later; a warning otherwise."""
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    allow = (
        f"allow it with LimitMEMLOCK=infinity under systemd (as {UNIT} does), "
        "`ulimit -l unlimited`, CAP_IPC_LOCK or root; or set realtime.lock_memory: false"
    )
    if soft != resource.RLIM_INFINITY and not _has_capability(CAP_IPC_LOCK):
        warnings.append(
            f"memory not locked: RLIMIT_MEMLOCK is {soft} bytes and without CAP_IPC_LOCK "
            f"every allocation past it would fail once locked; {allow}"
        )
        return False
    code = _mlockall(MCL_CURRENT | MCL_FUTURE)
    if code:
        warnings.append(
            f"memory not locked: mlockall failed ({os.strerror(code)}; RLIMIT_MEMLOCK "
            f"{_limit(soft)}): page faults can delay cycles; {allow}"
        )
    return code == 0


def _hold_cpu_latency(us: int, warnings: list[str]) -> int | None:
    """Ask the kernel to keep every CPU's wake-up latency within `us` for as long as the
    returned file stays open (closed by leave_realtime or at exit; not inherited by
    children); None, and a warning, where refused."""
    allow = (
        f"allow it with {CPU_LATENCY_RULE} (udev) and DeviceAllow={CPU_LATENCY} w under "
        f"systemd (as {UNIT} does) or root; or set realtime.cpu_latency_us: null to not ask"
    )
    try:
        held = os.open(CPU_LATENCY, os.O_WRONLY)
    except OSError as exc:
        warnings.append(
            f"CPU latency {us} us not held: {CPU_LATENCY}: {exc.strerror}: idle CPUs may "
            f"sleep in states slow to wake, which slows each of the cycle's wake-ups; {allow}"
        )
        return None
    try:
        os.write(held, struct.pack("=i", us))
    except OSError as exc:
        os.close(held)
        warnings.append(f"CPU latency {us} us not held: {CPU_LATENCY} refused it: {exc.strerror}")
        return None
    return held


def _set_fifo(priority: int, warnings: list[str]) -> int:
    """SCHED_FIFO at `priority` for this thread; the priority obtained, 0 if refused."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
        cgroup = (
            " (as root: the cgroup may have no real-time budget, cpu.rt_runtime_us with "
            "CONFIG_RT_GROUP_SCHED)"
            if os.geteuid() == 0 and exc.errno == errno.EPERM
            else ""
        )
        warnings.append(
            f"SCHED_FIFO priority {priority} refused ({exc.strerror}){cgroup}: the core "
            "runs at normal priority, where other processes can delay its cycles; allow "
            f"it with LimitRTPRIO={priority} and RestrictRealtime=no under systemd (as "
            f"{UNIT} does), `ulimit -r {priority}` (RLIMIT_RTPRIO, now {_limit(soft)}), "
            "CAP_SYS_NICE or root; or set realtime.priority: 0 to not ask"
        )
        return 0
    return priority


def _mlockall(flags: int) -> int:
    """mlockall(flags): 0, or the errno."""
    libc = _libc()
    return 0 if libc.mlockall(flags) == 0 else ctypes.get_errno()


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _has_capability(bit: int) -> bool:
    """Whether this process holds capability `bit` in its effective set."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return False
    for line in status.splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> bit & 1)
    return False


def _read_int(name: str) -> int | None:
    try:
        return int((PROC_SYS_KERNEL / name).read_text())
    except (OSError, ValueError):
        return None


def _online() -> str:
    try:
        return f"online here: {CPUS_ONLINE.read_text().strip()}"
    except OSError:
        return "online CPUs unknown"


def _limit(value: int) -> str:
    return "unlimited" if value == resource.RLIM_INFINITY else str(value)


def _cpu_list(cpus: frozenset[int]) -> str:
    return ",".join(map(str, sorted(cpus)))
