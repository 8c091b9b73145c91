"""The systemd unit and the networkd file in config/: syntax, settings, and the hardening."""

from __future__ import annotations

import configparser
import ctypes
import platform
import re
import shutil
import subprocess
import sys
import textwrap
from collections import defaultdict
from pathlib import Path

import pytest

from daemon.config import RealtimeConfig

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "config" / "cdprd.service"
NETWORK = ROOT / "config" / "80-can0.network"
NETWORKD = Path("/lib/systemd/systemd-networkd")
INSTALLED_EXEC = "/usr/local/bin/cdprd"


def unit_settings(text: str) -> dict[str, dict[str, list[str]]]:
    """section -> key -> values in order (unit files may repeat a key)."""
    sections: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        sections[section][key.strip()].append(value.strip())
    return sections


def test_unit_settings():
    service = unit_settings(UNIT.read_text())["Service"]
    assert service["Type"] == ["notify"]
    assert service["NotifyAccess"] == ["all"]  # the companion process notifies
    assert service["WatchdogSec"] == ["5"]
    assert service["Restart"] == ["on-failure"]
    assert service["KillSignal"] == ["SIGTERM"]
    assert service["ExecStart"] == [f"{INSTALLED_EXEC} run --config /etc/cdprd/cdprd.yaml"]
    assert service["DynamicUser"] == ["yes"]
    assert service["CapabilityBoundingSet"] == [""]
    assert service["MemoryDenyWriteExecute"] == ["yes"]
    assert service["ProtectSystem"] == ["strict"]
    assert service["NoNewPrivileges"] == ["yes"]
    families = service["RestrictAddressFamilies"][0].split()
    assert set(families) == {"AF_CAN", "AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}
    assert "PrivateNetwork" not in service  # the daemon needs the host's can0
    assert service["LogsDirectory"] == ["cdprd"] and service["StateDirectory"] == ["cdprd"]
    unit = unit_settings(UNIT.read_text())["Unit"]
    assert unit["StartLimitBurst"] and unit["StartLimitIntervalSec"]


def test_unit_permits_real_time_without_imposing_it():
    """The core raises its own priority and locks its memory (daemon.process.realtime):
    the unit permits both without a capability, up to the configured default priority,
    and schedules no process of the service real-time itself."""
    service = unit_settings(UNIT.read_text())["Service"]
    assert service["RestrictRealtime"] == ["no"]
    assert service["LimitRTPRIO"] == [str(RealtimeConfig().priority)]
    assert service["LimitMEMLOCK"] == ["infinity"]
    assert not {"CPUSchedulingPolicy", "CPUSchedulingPriority", "CPUAffinity"} & set(service)
    assert service["CapabilityBoundingSet"] == [""] and service["AmbientCapabilities"] == [""]
    # the system calls it makes pass the filter: @system-service holds them, and
    # ~@privileged does not take them away
    assert service["SystemCallFilter"] == ["@system-service", "~@privileged"]
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    needed = {"sched_setscheduler", "sched_setaffinity", "mlockall", "munlockall"}
    allowed, refused = _syscall_group("@system-service"), _syscall_group("@privileged")
    assert needed <= allowed and not needed & refused


def _syscall_group(group: str) -> set[str]:
    """The system calls in a systemd filter group, its nested groups expanded."""
    out = subprocess.run(
        ["systemd-analyze", "syscall-filter", group],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    names = {line.strip() for line in out.splitlines()[1:] if line.startswith(" ")}
    calls = {n for n in names if n and not n.startswith(("@", "#"))}
    for nested in {n for n in names if n.startswith("@")}:
        calls |= _syscall_group(nested)
    return calls


def _verify(tmp_path: Path, text: str) -> subprocess.CompletedProcess:
    """`systemd-analyze verify` on a copy whose ExecStart runs this interpreter (verify
    requires the program to exist); any message, even a warning, counts as a failure."""
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    copy = tmp_path / "cdprd.service"
    copy.write_text(text.replace(INSTALLED_EXEC, f"{sys.executable} -m daemon.cli"))
    return subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(copy)],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_unit_passes_systemd_analyze_verify(tmp_path):
    result = _verify(tmp_path, UNIT.read_text())
    assert result.returncode == 0 and not (result.stdout + result.stderr).strip(), (
        result.stdout + result.stderr
    )


def test_commented_options_are_valid_too(tmp_path):
    """The optional lines (device binding) verify when uncommented."""
    text = re.sub(r"(?m)^#([A-Z][A-Za-z]+=)", r"\1", UNIT.read_text())
    assert unit_settings(text)["Unit"]["BindsTo"] == ["sys-subsystem-net-devices-can0.device"]
    result = _verify(tmp_path, text)
    output = (result.stdout + result.stderr).strip()
    # the can0 device unit does not exist on a build machine; nothing else may complain
    assert result.returncode == 0, output
    assert all("sys-subsystem-net-devices-can0.device" in line for line in output.splitlines())


def test_verify_catches_a_typo(tmp_path):
    """Guards the check above: a misspelt key must produce output."""
    result = _verify(tmp_path, UNIT.read_text().replace("WatchdogSec=", "WatchDogSec="))
    assert "Unknown key" in result.stdout + result.stderr


def test_network_file():
    parser = configparser.ConfigParser(strict=True, interpolation=None)
    parser.optionxform = str  # keys are case-sensitive in systemd
    parser.read_string(NETWORK.read_text())
    assert parser["Match"]["Name"] == "can0"
    assert parser["CAN"]["BitRate"] == "1M"
    assert parser["CAN"]["RestartSec"] == "100ms"
    assert parser["Link"]["RequiredForOnline"] == "no"
    if not NETWORKD.exists():
        pytest.skip(f"{NETWORKD} not installed: key names not checked against networkd")
    known = NETWORKD.read_bytes()  # networkd's key table holds "Section.Key" strings
    for section in parser.sections():
        for key in parser[section]:
            assert b"\0" + f"{section}.{key}".encode() + b"\0" in known, f"{section}.{key}"


# -- MemoryDenyWriteExecute ------------------------------------------------------------------

MDWE_PROBE = textwrap.dedent(
    """
    import ctypes, mmap, sys
    libc = ctypes.CDLL(None, use_errno=True)

    class Insn(ctypes.Structure):
        _fields_ = [("code", ctypes.c_uint16), ("jt", ctypes.c_uint8),
                    ("jf", ctypes.c_uint8), ("k", ctypes.c_uint32)]

    class Prog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_uint16), ("filter", ctypes.POINTER(Insn))]

    # systemd's MemoryDenyWriteExecute rules (x86-64): mmap with PROT_WRITE|PROT_EXEC,
    # mprotect/pkey_mprotect adding PROT_EXEC, shmat with SHM_EXEC fail with EPERM.
    LD, JEQ, AND, RET = 0x20, 0x15, 0x54, 0x06
    ALLOW, EPERM, ARG2 = 0x7FFF0000, 0x00050001, 32
    def check(mask, value):
        return [(LD, 0, 0, ARG2), (AND, 0, 0, mask), (JEQ, 0, 1, value),
                (RET, 0, 0, EPERM), (RET, 0, 0, ALLOW)]
    prog = [(LD, 0, 0, 4), (JEQ, 1, 0, 0xC000003E), (RET, 0, 0, ALLOW), (LD, 0, 0, 0)]
    prog += [(JEQ, 0, 5, 9)] + check(6, 6)
    prog += [(JEQ, 1, 0, 10), (JEQ, 0, 5, 329)] + check(4, 4)
    prog += [(JEQ, 0, 5, 30)] + check(0x8000, 0x8000) + [(RET, 0, 0, ALLOW)]
    insns = (Insn * len(prog))(*[Insn(*i) for i in prog])
    assert libc.prctl(38, 1, 0, 0, 0) == 0  # PR_SET_NO_NEW_PRIVS
    if libc.prctl(22, 2, ctypes.byref(Prog(len(prog), insns)), 0, 0) != 0:
        sys.exit(77)  # seccomp unavailable
    page = mmap.mmap(-1, 4096)
    address = ctypes.addressof(ctypes.c_char.from_buffer(page))
    assert libc.mprotect(ctypes.c_void_p(address), 4096, 5) == -1, "filter not active"

    import numpy as np, scipy.linalg, scipy.signal, scipy.sparse as sp
    from scipy.spatial.transform import RotationSpline
    import osqp, can, mcap.writer, io, zenoh, pydantic, yaml
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.eye(2)), np.zeros(2), sp.csc_matrix(np.eye(2)),
                 np.ones(2), 2 * np.ones(2), verbose=False)
    assert abs(solver.solve().x[0] - 1) < 1e-2
    bus = can.Bus(interface="virtual", channel="mdwe")
    bus.shutdown()
    writer = mcap.writer.Writer(io.BytesIO())
    writer.start()
    writer.finish()
    callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int)(lambda x: x + 1)
    assert callback(1) == 2
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    zenoh.open(config).close()
    print("ok")
    """
)


@pytest.mark.skipif(
    sys.platform != "linux" or platform.machine() != "x86_64", reason="x86-64 Linux seccomp"
)
def test_software_stack_runs_under_memory_deny_write_execute():
    """The unit sets MemoryDenyWriteExecute=yes: numpy, scipy, OSQP, python-can, mcap,
    zenoh and ctypes callbacks must work with the same seccomp rules in force."""
    assert ctypes.sizeof(ctypes.c_void_p) == 8
    result = subprocess.run(
        [sys.executable, "-c", MDWE_PROBE], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    if result.returncode == 77:
        pytest.skip("seccomp filters are not available here")
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-3000:]
