"""The exit codes of `cdprd` commands, one table for all of them (the CLI reference prints
it: daemon.cli.reference)."""

from __future__ import annotations

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
