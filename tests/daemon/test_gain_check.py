"""check-config and run refuse gains the home modal masses make unstable (daemon.cli.gain_check)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from daemon.cli import analyze_cmd, main, run_cmd
from daemon.cli.gain_check import check_gains
from tests.daemon.test_cli import CONFIG, NAMED
from tuning.workspace_analysis import rig_for, robustness

SHIPPED = sorted(CONFIG.glob("reference8-*.yaml"))
LINE = re.compile(
    r"^controller stability: stable for modal masses up to ([0-9.]+) kg \(largest at home "
    r"9.49 kg, margin x[0-9.]+\); tolerates (at least )?[0-9.]+ ms (\(the scan's end\) )?of "
    r"command delay",
    re.M,
)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_the_shipped_configs_pass_and_print_their_stability(
    path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check-config", str(path)]) == 0, capsys.readouterr().err
    assert LINE.search(capsys.readouterr().out)


def test_the_largest_stable_mass_is_analyzes(capsys: pytest.CaptureFixture[str]) -> None:
    """The same number as `cdprd analyze`'s robustness line, computed without its sweep's
    step responses; and the drives' force lag is in the loop."""
    path = str(CONFIG / "reference8-cia402.yaml")
    analysed = robustness(rig_for(*analyze_cmd.load_config(path))).largest_stable_mass
    check = check_gains(run_cmd.load_checked(path))
    assert check.largest_stable_mass == analysed
    assert main(["check-config", path]) == 0
    match = LINE.search(capsys.readouterr().out)
    assert match and match[1] == f"{analysed:.3g}"
    slower = run_cmd.load_checked(path, lambda data: data["drives"].update(force_lag=0.01))
    assert check_gains(slower).largest_stable_mass != analysed


def test_run_refuses_unstable_gains_before_it_opens_a_bus(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    opened = []
    monkeypatch.setattr(run_cmd, "open_bus", lambda config: opened.append(config))
    path = tmp_path / "cdprd.yaml"
    text, problem = NAMED["a kd too high for a home mode"]
    path.write_text(text)
    with pytest.raises(SystemExit) as stopped:
        main(["run", "--config", str(path)])
    assert stopped.value.code == 1 and not opened
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {path}: {problem}") and "`cdprd tune`" in line
