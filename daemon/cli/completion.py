"""`cdprd completion bash`: a bash completion script written from the argument parser, so
that it offers every subcommand and option the installed cdprd has.

    cdprd completion bash > /etc/bash_completion.d/cdprd     # or, for this shell:
    source <(cdprd completion bash)

After a subcommand it offers that subcommand's options after a "-", and file names
otherwise (configs, robot files, recordings and trajectories are the usual arguments)."""

from __future__ import annotations

import argparse
import shlex

SHELLS = ("bash",)


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's subcommands by name (empty if it has none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> list[str]:
    return [s for action in parser._actions for s in action.option_strings]


def bash_completion(parser: argparse.ArgumentParser) -> str:
    """The bash script: a function `_cdprd` registered with `complete -F`."""
    subs = subcommands(parser)
    words = " ".join([*subs, *_options(parser)])
    cases = [
        f"        {shlex.quote(name)}) opts={shlex.quote(' '.join(_options(sub)))} ;;"
        for name, sub in subs.items()
    ]
    lines = [
        "# bash completion for cdprd, written by `cdprd completion bash`",
        "_cdprd() {",
        '    local cur="${COMP_WORDS[COMP_CWORD]}" opts=""',
        '    if [ "$COMP_CWORD" -eq 1 ]; then',
        f'        COMPREPLY=($(compgen -W "{words}" -- "$cur"))',
        "        return",
        "    fi",
        '    case "${COMP_WORDS[1]}" in',
        *cases,
        "    esac",
        '    if [[ "$cur" == -* ]]; then',
        '        COMPREPLY=($(compgen -W "$opts" -- "$cur"))',
        "    else",
        '        COMPREPLY=($(compgen -f -- "$cur"))',
        "    fi",
        "}",
        "complete -o filenames -F _cdprd cdprd",
    ]
    return "\n".join(lines) + "\n"


def add_parser(sub: argparse._SubParsersAction, root: argparse.ArgumentParser) -> None:
    """`cdprd completion SHELL`, completing what `root` (the whole command line) takes."""
    p = sub.add_parser(
        "completion",
        help="print a shell completion script",
        description="Print a completion script for SHELL: `source <(cdprd completion bash)`, "
        "or save it as /etc/bash_completion.d/cdprd.",
    )
    p.add_argument("shell", choices=SHELLS)

    def handler(args: argparse.Namespace) -> int:
        print(bash_completion(root), end="")
        return 0

    p.set_defaults(handler=handler)
