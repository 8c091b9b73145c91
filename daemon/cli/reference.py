"""The CLI reference page, written from the argument parser itself so that it cannot
drift from the code: `python -m daemon.cli.reference > docs/reference/cli.md`
(tests/test_docs.py fails while the committed page differs)."""

from __future__ import annotations

import os
from unittest import mock

from daemon.cli import command_parser
from daemon.cli.completion import subcommands
from daemon.cli.exit_codes import EXIT_CODES

WIDTH = "100"  # columns of the help texts, whatever the terminal


def cli_reference() -> str:
    """Markdown: each subcommand of `cdprd` with its help, as `cdprd NAME --help` prints it."""
    with mock.patch.dict(os.environ, {"COLUMNS": WIDTH}):
        parser = command_parser()
        parts = [
            "# CLI reference",
            "",
            "Written from the command's own parser by `python -m daemon.cli.reference`; "
            "`cdprd COMMAND --help` prints the same.",
            "",
            "```text",
            parser.format_help().rstrip(),
            "```",
        ]
        for name, sub in subcommands(parser).items():
            parts += ["", f"## cdprd {name}", "", "```text", sub.format_help().rstrip(), "```"]
    parts += ["", "## Exit codes", "", "| code | meaning |", "|---|---|"]
    parts += [f"| {code} | {meaning} |" for code, meaning in EXIT_CODES.items()]
    return "\n".join(parts) + "\n"


if __name__ == "__main__":
    print(cli_reference(), end="")
