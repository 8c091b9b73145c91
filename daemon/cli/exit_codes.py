"""The exit codes of `cdprd` commands, one table for all of them (the CLI reference prints
it: daemon.cli.reference)."""

from __future__ import annotations

from collections.abc import Mapping

from daemon.process.wire import OTHER_CODE
from daemon.service.service import EXIT_BUS_LOST

EXIT_OK = 0
EXIT_FAILED = 1  # refused by the daemon, a failed procedure, or a config with problems
EXIT_USAGE = 2  # bad arguments, or a config `run` cannot run
EXIT_UNREACHABLE = 3  # no daemon answered
EXIT_ABORTED = 3  # tune: the experiment aborted and braked

EXIT_CODES: dict[int, str] = {
    EXIT_OK: "success",
    EXIT_FAILED: "the daemon refused the command, the procedure failed (calibrate, tune, "
    "identify-payload), or check-config found problems (each is printed)",
    EXIT_USAGE: "bad arguments, or a config the command cannot use (the problem is printed)",
    EXIT_UNREACHABLE: "client commands: no daemon answered on the zenoh endpoint; `tune`: "
    "the experiment aborted and braked (the reason is printed); `run`: its companion "
    "process runs other code than its core (the installed cdprd changed under a running "
    "service: restart it)",
    EXIT_BUS_LOST: "`run`: the CAN bus was lost; the daemon braked and exits for the "
    "service manager to restart it",
}
assert OTHER_CODE == EXIT_ABORTED == EXIT_UNREACHABLE  # the table's entry for 3 says all

CLIENT_CODES: dict[int, str] = {
    EXIT_OK: "done",
    EXIT_FAILED: "the daemon refused (the reason is printed), or a motion waited for "
    "(--wait) braked or was stopped",
    EXIT_USAGE: "bad arguments, an unreadable file, several daemons and no --prefix",
    EXIT_UNREACHABLE: "no daemon reachable",
}
CHECKS: dict[int, str] = {EXIT_OK: "done", EXIT_FAILED: "a config with problems (each is printed)"}
COMMAND_CODES: dict[str, dict[int, str]] = {  # the commands that are not daemon clients
    "check-config": CHECKS,
    "analyze": {**CHECKS, EXIT_FAILED: "a config with problems, or plots not written"},
    "workspace": {**CHECKS, EXIT_FAILED: "a config with problems, or the map not saved"},
    "plan": {
        EXIT_OK: "timed, and the daemon's validation accepts it",
        EXIT_FAILED: "no timing holds the tensions, or the validation refuses it",
        EXIT_USAGE: "a config or path with problems, bad arguments",
    },
    "tune": {
        EXIT_OK: "done",
        EXIT_FAILED: "a config or request with problems",
        EXIT_ABORTED: "the experiment (or a --check-loads step) aborted and braked",
    },
    "calibrate": {
        **CLIENT_CODES,
        EXIT_FAILED: "the daemon refused, or the calibration failed (the reason is printed)",
    },
    "run": {
        EXIT_OK: "stopped (SIGTERM, SIGINT)",
        EXIT_FAILED: "a simulator that cannot be built or started",
        EXIT_USAGE: "a config `run` cannot run",
        EXIT_UNREACHABLE: "the companion process runs other code than the core: restart it",
        EXIT_BUS_LOST: "the CAN bus was lost; the daemon braked and exits for the service "
        "manager to restart it",
    },
    "sim": {EXIT_OK: "stopped", EXIT_FAILED: "a config with problems", EXIT_USAGE: "bad arguments"},
    "demo": {
        EXIT_OK: "the demo ran",
        EXIT_FAILED: "it did not complete (the reason is printed), or it did not end holding "
        "within 5 mm RMS (its figures are printed)",
    },
    "completion": {EXIT_OK: "printed"},
}


def codes_of(command: str) -> dict[int, str]:
    """The exit codes of `command` (a daemon client's unless COMMAND_CODES has it)."""
    return COMMAND_CODES.get(command, CLIENT_CODES)


def epilog(codes: Mapping[int, str]) -> str:
    """A command's --help epilog: its exit codes (the table for all: EXIT_CODES)."""
    return "exit codes: " + "; ".join(f"{code} {meaning}" for code, meaning in codes.items())
