"""How every `cdprd` command prints its result: human text, or with --json one JSON
object on stdout, and errors the same way (the human line on stderr, or
{"error": {"code", "reason", ...}} on stdout), so that a script reads stdout alone and
the exit code (daemon.cli.exit_codes) tells success from failure.  The command line's
own errors (a missing or malformed argument) too: CommandParser."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn

import numpy as np
import yaml

from daemon.cli.exit_codes import EXIT_USAGE

JSON_HELP = 'print the result as one JSON object on stdout (errors too: {"error": ...})'


def add_json_flag(parser: argparse.ArgumentParser, help: str = JSON_HELP) -> None:
    """The --json option (`args.json`)."""
    parser.add_argument("--json", action="store_true", help=help)


def plain(value: Any) -> Any:
    """numpy scalars to Python, non-finite floats to None, recursively: strict JSON."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer | int):
        return int(value)
    if isinstance(value, np.floating | float):
        return float(value) if math.isfinite(value) else None
    return value


def print_result(
    result: Mapping[str, Any], as_json: bool, human: Callable[[], None] | None = None
) -> None:
    """`result` as one JSON line (as_json), else `human()` prints it (None: the result
    as YAML, a mapping a person reads)."""
    if as_json:
        print(json.dumps(plain(dict(result)), allow_nan=False), flush=True)
    elif human is not None:
        human()
    else:
        print(yaml.safe_dump(plain(dict(result)), sort_keys=False, width=100).rstrip())


def print_error(
    code: str, reason: str, as_json: bool, details: Mapping[str, Any] | None = None, *,
    prefix: str = "error",
) -> None:  # fmt: skip
    """An error: {"error": {"code", "reason", **details}} on stdout (as_json), else
    `prefix: reason` on stderr with the details as JSON on the next line."""
    if as_json:
        error = {"code": code, "reason": reason, **(details or {})}
        print(json.dumps(plain({"error": error}), allow_nan=False), flush=True)
        return
    print(f"{prefix}: {reason}", file=sys.stderr)
    if details:
        print(f"  {json.dumps(plain(dict(details)))}", file=sys.stderr)


class CommandParser(argparse.ArgumentParser):
    """An ArgumentParser (its subcommands' parsers too) whose errors, on a command line
    with --json, are {"error": {"code": "usage", "reason"}} on stdout and exit code 2,
    like the commands' own usage errors; without --json argparse's usage and message on
    stderr, exit code 2, as ever."""

    json_errors = False  # set from the arguments each parse is given

    def parse_known_args(
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """argparse's, remembering whether `args` ask for --json (a subcommand's parser
        is given the arguments after the subcommand's name, where --json is)."""
        given = list(sys.argv[1:] if args is None else args)
        options = given[: given.index("--")] if "--" in given else given
        self.json_errors = "--json" in options
        return super().parse_known_args(given, namespace)

    def error(self, message: str) -> NoReturn:
        """Exit 2 naming the problem: as JSON on stdout if asked, else argparse's way."""
        if self.json_errors:
            print_error("usage", message, as_json=True)
            self.exit(EXIT_USAGE)
        super().error(message)
