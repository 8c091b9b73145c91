"""The cdprd command line: check-config summarises a sound file, names problems in a bad one."""

from __future__ import annotations

from pathlib import Path

import pytest

from daemon.cli import main
from tests.conftest import ROBOTS


def test_check_config_summarises_a_robot(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(ROBOTS / "reference8.yaml")]) == 0
    out = capsys.readouterr().out
    assert "robot reference8: 8 cables, platform 10 kg" in out
    assert "modal masses at home (Lemma 1, kg): 2.41" in out


def test_check_config_fails_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROBOTS / "reference8.yaml").read_text().replace("mass: 10.0", "mass: -10.0")
    (tmp_path / "r.yaml").write_text(text)
    assert main(["check-config", str(tmp_path / "r.yaml")]) == 1
    assert "platform.mass: Input should be greater than 0 (got -10.0)" in capsys.readouterr().err
