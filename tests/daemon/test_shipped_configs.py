"""Every config shipped in config/ passes `cdprd check-config` with the robot it names.

The hardware template names files the operator provides (/etc/cdprd/robot.yaml, the
drive's EDS beside the config); it is checked with the EDS in config/can and reference8
with its crossed cables routed clear (tests/data/robots/reference8-offset.yaml: the
template keeps the interference check on, as a real robot should) in their place."""

from __future__ import annotations

from pathlib import Path

import pytest

from daemon.cli import main
from tests.conftest import OFFSET8, ROBOTS

CONFIG = ROBOTS.parent
# what the template names that only exists on the operator's machine -> its stand-in
STAND_INS = {
    "hardware-template.yaml": {
        "robot: /etc/cdprd/robot.yaml": f"robot: {OFFSET8}",
        "eds: drive.eds": f"eds: {CONFIG / 'can' / 'cia402_cst.eds'}",
    }
}
SHIPPED = sorted(p.name for p in CONFIG.glob("*.yaml")) + sorted(
    f"robots/{p.name}" for p in ROBOTS.glob("*.yaml")
)


def test_every_config_file_is_covered() -> None:
    assert "hardware-template.yaml" in SHIPPED and "robots/reference8.yaml" in SHIPPED
    found = {p.relative_to(CONFIG).as_posix() for p in CONFIG.rglob("*.y*ml")}
    assert found == set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_config_passes_check_config(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = CONFIG / name
    stand_ins = STAND_INS.get(name)
    if stand_ins:
        text = path.read_text()
        for old, new in stand_ins.items():
            assert old in text, old
            text = text.replace(old, new)
        path = tmp_path / path.name
        path.write_text(text)
    code = main(["check-config", str(path)])
    assert code == 0, capsys.readouterr().err
