"""Run a command next to a real SocketCAN ``vcan0``, inside User-Mode Linux if need be.

Some kernels (this project's CI among them) have no SocketCAN, so ``vcan0``
cannot be created there.  Debian's ``user-mode-linux`` package ships a Linux
6.1 kernel that runs as an ordinary process (``linux.uml``) together with the
CAN modules, so this module boots it with the host's root directory as a
read-only hostfs, loads ``can``, ``can-dev``, ``can-raw`` and ``vcan``, brings
up ``lo``, ``vcan0`` and ``vcan1`` (no other network), mounts the working directory and a
run directory read-write at their host paths, runs one command there with the
output streamed back, and powers the guest off.  The guest's exit code comes
back through a file in the run directory.

Command line::

    python tests/vcan/uml.py [--timeout S] [--cwd DIR] [-e NAME=VALUE] -- COMMAND...

The functions :func:`native_vcan_reason` and :func:`uml_reason` say whether a
native ``vcan0`` or a bootable UML is at hand (``None``), or why not.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

CHANNEL = "vcan0"
CHANNELS = ("vcan0", "vcan1")  # the guest's interfaces (drives on two buses need both)
GUEST_ENV = "CDPR_IN_UML"
"""Set to ``1`` in the guest's environment."""
DEFAULT_TIMEOUT = 1200.0  # the whole vcan suite in one guest: ~6-10 min on a 2-CPU host
INSTALL_HINT = "apt-get install user-mode-linux busybox-static can-utils gcc"

KERNEL = "linux.uml"
SOFTIRQ_PRIORITY = 50  # SCHED_FIFO of the guest's ksoftirqd: above every test process
MODULES_ROOT = Path("/usr/lib/uml/modules")
CAN_MODULES = (
    "kernel/net/can/can.ko",
    "kernel/drivers/net/can/dev/can-dev.ko",
    "kernel/net/can/can-raw.ko",
    "kernel/drivers/net/can/vcan.ko",
)
GUEST_MEMORY = "2G"  # each daemon core locks ~0.5 GB (its heap, libraries, the curve ring)
SHIM_SOURCE = Path(__file__).with_name("xstate_shim.c")
READY_LINE = "cdpr-uml: guest ready"
EXIT_FILE = "exit-code"

# Host variables handed to the guest command; everything else starts empty.
PASSED_ENV = ("HOME", "LANG", "LC_ALL", "PYTHONPATH", "VIRTUAL_ENV", "COLUMNS")
# Page faults are costly under UML: keep freed memory instead of returning it.
MALLOC_TUNABLES = (
    "glibc.malloc.mmap_threshold=268435456:"
    "glibc.malloc.trim_threshold=1073741824:"
    "glibc.malloc.top_pad=67108864"
)


@dataclass(frozen=True)
class GuestRun:
    """Outcome of one :func:`run_in_uml` call."""

    exit_code: int | None
    """The command's exit code; ``None`` if the guest never reported one."""
    output: str
    """Everything the guest printed (kernel, init and command), ``\\r`` removed."""
    boot_seconds: float | None
    """Time from starting ``linux.uml`` until the command started."""
    total_seconds: float
    timed_out: bool


@functools.cache
def native_vcan_reason(channel: str = CHANNEL) -> str | None:
    """Say why ``channel`` cannot be used on this kernel, or ``None`` if it can.

    A missing ``channel`` is created with ``ip link add ... type vcan`` when
    possible (root, a kernel with the vcan module), as a developer would.
    """
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no socket.AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return f"the kernel has no SocketCAN CAN_RAW sockets ({exc.strerror})"
    if not Path("/sys/class/net", channel).exists():
        problem = _ip("link", "add", "dev", channel, "type", "vcan")
        if problem:
            return f"no {channel} and it cannot be created: {problem}"
    if not _is_up(channel):
        problem = _ip("link", "set", "up", channel)
        if problem:
            return f"{channel} is down and cannot be set up: {problem}"
    return None


def _ip(*args: str) -> str | None:
    """Run ``ip ARGS``; return its complaint, or ``None`` on success."""
    if shutil.which("ip") is None:
        return "no 'ip' command (apt-get install iproute2)"
    done = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    return (done.stderr.strip() or f"exit code {done.returncode}") if done.returncode else None


def _is_up(channel: str) -> bool:
    flags = Path("/sys/class/net", channel, "flags").read_text()
    return bool(int(flags, 16) & 0x1)  # IFF_UP


def modules_dir() -> Path | None:
    """The UML kernel's module tree (``/usr/lib/uml/modules/<version>``), if any."""
    versions = sorted(MODULES_ROOT.glob("*/kernel")) if MODULES_ROOT.is_dir() else []
    return versions[-1].parent if versions else None


def uml_reason() -> str | None:
    """Say what is missing to boot UML with vcan here, or ``None`` if nothing is."""
    missing = [name for name in (KERNEL, "busybox", "candump", "cc") if shutil.which(name) is None]
    modules = modules_dir()
    if modules is None:
        missing.append(f"UML kernel modules under {MODULES_ROOT}")
    else:
        missing += [m for m in CAN_MODULES if not (modules / m).is_file()]
    if missing:
        return f"missing {', '.join(missing)} ({INSTALL_HINT})"
    return None


def guest_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment the guest command gets.

    ``PATH`` starts with this interpreter's directory, so ``python`` and
    ``pytest`` there are the real ones rather than a version manager's shims.
    """
    env = {name: os.environ[name] for name in PASSED_ENV if name in os.environ}
    env.update(
        PATH=os.pathsep.join(
            [str(Path(sys.executable).parent), os.environ.get("PATH", os.defpath)]
        ),
        TMPDIR="/tmp",
        GLIBC_TUNABLES=MALLOC_TUNABLES,
        **{GUEST_ENV: "1"},
    )
    env.update(extra or {})
    return env


def _init_script(
    *,
    busybox: str,
    modules: Path,
    writable: Iterable[Path],
    cwd: Path,
    env: Mapping[str, str],
    command: Sequence[str],
    exit_file: Path,
) -> str:
    """The guest's PID 1: a busybox shell script."""
    q = shlex.quote
    lines = [
        f"#!{busybox} sh",
        "# PID 1 of a UML guest, written by tests/vcan/uml.py.",
        f"bb={q(busybox)}",
        'fail() { echo "cdpr-uml: $*" >&2; $bb sync; $bb poweroff -f; }',
        "$bb mount -t proc proc /proc || fail mount /proc",
        "$bb mount -t sysfs sysfs /sys || fail mount /sys",
        "$bb grep -q ' /dev ' /proc/mounts || $bb mount -t devtmpfs dev /dev || fail mount /dev",
        "$bb mkdir -p /dev/shm && $bb mount -t tmpfs tmpfs /dev/shm || fail mount /dev/shm",
        "$bb mount -t tmpfs tmpfs /tmp || fail mount /tmp",
        "$bb mount -t tmpfs tmpfs /run || fail mount /run",
    ]
    for path in writable:
        p = q(str(path))
        lines.append(f"$bb mkdir -p {p} && $bb mount -t hostfs -o {p} hostfs {p} || fail mount {p}")
    for module in CAN_MODULES:
        lines.append(f"$bb insmod {q(str(modules / module))} || fail insmod {module}")
    lines += [
        "$bb ip link set dev lo up || fail lo up",
        *(f"$bb ip link add dev {c} type vcan || fail add {c}" for c in CHANNELS),
        *(f"$bb ip link set dev {c} up || fail {c} up" for c in CHANNELS),
        # Frames reach a receiving socket in the NET_RX softirq, which under load the
        # kernel hands to ksoftirqd: at normal priority, the real-time simulator and
        # daemon starved it and answers sent on time reached the daemon 40 ms late, in
        # bulk (every drive went stale).  Above them, as a PREEMPT_RT kernel's interrupt
        # threads are (SCHED_FIFO 50).
        "for d in /proc/[0-9]*; do read -r comm < $d/comm; case $comm in ksoftirqd/*)"
        f" /usr/bin/chrt -f -p {SOFTIRQ_PRIORITY} ${{d#/proc/}} || fail chrt ksoftirqd;;"
        " esac; done",
        f"cd {q(str(cwd))} || fail cd",
        f"echo {q(READY_LINE)}",
        " ".join(
            # The host's env, not busybox's: busybox would prefer its applets to host programs.
            [
                "/usr/bin/env -i",
                *(q(f"{k}={v}") for k, v in env.items()),
                *map(q, command),
                "</dev/null",
            ]
        ),
        f"echo $? > {q(str(exit_file))}",
        "$bb sync",
        "$bb poweroff -f",
    ]
    return "\n".join(lines) + "\n"


def _build_shim(run_dir: Path) -> Path:
    """Compile ``xstate_shim.c`` (see there: UML 6.1 needs it on AVX-512 hosts)."""
    shim = run_dir / "xstate_shim.so"
    argv = ["cc", "-O2", "-shared", "-fPIC", "-o", str(shim), str(SHIM_SOURCE), "-ldl"]
    done = subprocess.run(argv, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"cannot build {SHIM_SOURCE.name}: {done.stderr.strip()}")
    return shim


def _pin_to_one_cpu() -> None:
    """UML runs about 3x faster when its processes share one CPU."""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def run_in_uml(
    command: Sequence[str],
    *,
    cwd: Path | None = None,
    writable: Sequence[Path] = (),
    env: Mapping[str, str] | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    echo: TextIO | None = None,
) -> GuestRun:
    """Boot UML, run ``command`` in ``cwd`` with ``vcan0`` and ``vcan1`` up, and power off.

    ``cwd`` (default: the current directory) and ``writable`` are mounted
    read-write at their host paths; the rest of the host is read-only.  The
    command's environment is :func:`guest_env` plus ``env``.  The guest's
    output is copied line by line to ``echo``, if given, as it comes.  After
    ``timeout`` seconds UML's whole process group is killed.
    """
    missing = uml_reason()
    if missing:
        raise RuntimeError(f"cannot boot user-mode-linux: {missing}")
    cwd = (cwd or Path.cwd()).resolve()
    # Under /tmp, not $TMPDIR: the guest's devtmpfs would hide an init under /dev/shm.
    with tempfile.TemporaryDirectory(prefix="cdpr-uml-", dir="/tmp") as tmp:
        run_dir = Path(tmp)
        busybox = shutil.which("busybox")
        kernel = shutil.which(KERNEL)
        modules = modules_dir()
        assert busybox and kernel and modules  # checked by uml_reason()
        init = run_dir / "init"
        init.write_text(
            _init_script(
                busybox=busybox,
                modules=modules,
                writable=[cwd, run_dir, *(Path(p).resolve() for p in writable)],
                cwd=cwd,
                env=guest_env(env),
                command=command,
                exit_file=run_dir / EXIT_FILE,
            )
        )
        init.chmod(0o755)
        host_env = dict(os.environ, LD_PRELOAD=str(_build_shim(run_dir)))
        if os.access("/dev/shm", os.W_OK):
            host_env["TMPDIR"] = "/dev/shm"  # UML's guest memory is a file in TMPDIR
        argv = [
            kernel,
            f"mem={GUEST_MEMORY}",
            "root=/dev/root",
            "rootfstype=hostfs",
            "rootflags=/",
            "ro",
            f"init={init}",
            "con=null",
            "con0=null,fd:1",
            "con1=null,fd:2",
            "ssl=null",
            f"uml_dir={run_dir}",  # UML's pid file and mconsole socket; not ~/.uml
            "umid=guest",
            "quiet",
        ]
        return _supervise(argv, host_env, run_dir / EXIT_FILE, timeout, echo)


def _supervise(
    argv: list[str], env: dict[str, str], exit_file: Path, timeout: float, echo: TextIO | None
) -> GuestRun:
    """Run UML, relay its output, and always kill its process group at the end."""
    lines: list[str] = []
    ready_at: list[float] = []
    start = time.monotonic()
    proc = subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,  # UML calls setsid() anyway; its group is ours to kill
        preexec_fn=_pin_to_one_cpu,
    )
    assert proc.stdout is not None

    def relay() -> None:
        for raw in proc.stdout:
            line = raw.decode(errors="replace").replace("\r", "")
            if line.rstrip("\n") == READY_LINE and not ready_at:
                ready_at.append(time.monotonic())
            lines.append(line)
            if echo is not None:
                echo.write(line)
                echo.flush()

    reader = threading.Thread(target=relay, daemon=True)
    reader.start()
    timed_out = False
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        timed_out = True
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # also UML's helper processes
        proc.wait()
        reader.join(timeout=5)
    total = time.monotonic() - start
    if timed_out:
        lines.append(f"cdpr-uml: killed after {timeout:g} s\n")
    code = exit_file.read_text().strip() if exit_file.exists() else ""
    return GuestRun(
        exit_code=int(code) if code.lstrip("-").isdigit() else None,
        output="".join(lines),
        boot_seconds=ready_at[0] - start if ready_at else None,
        total_seconds=total,
        timed_out=timed_out,
    )


def _assignment(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return name, value


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the guest command's exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--timeout", type=float, default=DEFAULT_TIMEOUT, help="seconds (default %(default)s)"
    )
    parser.add_argument(
        "--cwd", type=Path, help="working directory, mounted read-write (default: .)"
    )
    parser.add_argument(
        "-e", "--env", action="append", default=[], type=_assignment, metavar="NAME=VALUE"
    )
    parser.add_argument("command", nargs="+", help="the command to run in the guest (after --)")
    args = parser.parse_args(argv)
    missing = uml_reason()
    if missing:
        print(f"uml: cannot boot user-mode-linux: {missing}", file=sys.stderr)
        return 2
    result = run_in_uml(
        args.command, cwd=args.cwd, env=dict(args.env), timeout=args.timeout, echo=sys.stdout
    )
    boot = f"{result.boot_seconds:.2f} s" if result.boot_seconds is not None else "not reached"
    print(
        f"uml: boot {boot}, total {result.total_seconds:.2f} s, exit code {result.exit_code}"
        + (" (timed out)" if result.timed_out else ""),
        file=sys.stderr,
    )
    return result.exit_code if result.exit_code is not None else 125


if __name__ == "__main__":
    sys.exit(main())
