"""`cdprd completion bash`: the script it prints, sourced into a real bash, completes
subcommands, each subcommand's own options, and file names."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from daemon.cli import command_parser, main
from daemon.cli.completion import bash_completion, subcommands


def _complete(script: Path, cwd: Path, *words: str) -> list[str]:
    """What `_cdprd` offers for the command line `cdprd WORDS...` (the last word the one
    being completed)."""
    line = " ".join(["cdprd", *words])
    program = (
        f"source {script}; COMP_WORDS=({line}); COMP_CWORD={len(words)}; _cdprd; "
        'printf "%s\\n" "${COMPREPLY[@]}"'
    )
    result = subprocess.run(
        ["bash", "--norc", "--noprofile", "-c", program],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    return [w for w in result.stdout.splitlines() if w]


@pytest.fixture
def script(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Path:
    assert main(["completion", "bash"]) == 0
    path = tmp_path / "cdprd.bash"
    path.write_text(capsys.readouterr().out)
    assert path.read_text() == bash_completion(command_parser())
    return path


def test_it_completes_subcommands(script: Path, tmp_path: Path) -> None:
    assert _complete(script, tmp_path, "ca") == ["calibrate"]
    assert set(_complete(script, tmp_path, "")) >= set(subcommands(command_parser()))


def test_it_completes_a_subcommands_own_options(script: Path, tmp_path: Path) -> None:
    assert _complete(script, tmp_path, "calibrate", "--po") == ["--poses"]
    assert "--poses" not in _complete(script, tmp_path, "demo", "--")
    assert "--plot" in _complete(script, tmp_path, "demo", "--")


def test_it_completes_file_names(script: Path, tmp_path: Path) -> None:
    (tmp_path / "robot-a.yaml").write_text("")
    (tmp_path / "robot-b.yaml").write_text("")
    # in directory order (bash sorts what it shows): tmpfs lists the newest first
    assert sorted(_complete(script, tmp_path, "run", "robot-")) == ["robot-a.yaml", "robot-b.yaml"]
