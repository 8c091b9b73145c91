"""check-config and run refuse gains the home modal masses make unstable (daemon.cli.gain_check)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

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
    robot, spec, force_lag = analyze_cmd.load_config(path)
    analysed = robustness(rig_for(robot, spec, force_lag=force_lag)).largest_stable_mass
    check = check_gains(run_cmd.load_checked(path))
    assert check.largest_stable_mass == analysed
    assert main(["check-config", path]) == 0
    match = LINE.search(capsys.readouterr().out)
    assert match and match[1] == f"{analysed:.3g}"
    slower = run_cmd.load_checked(path, lambda data: data["drives"].update(force_lag=0.01))
    assert check_gains(slower).largest_stable_mass != analysed


def test_analyze_flies_the_daemon_configs_force_lag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cdprd analyze` of a daemon config whose drives lag 10 ms reports the largest
    stable mass check-config finds for it, not the 2 ms default's."""
    data = yaml.safe_load((CONFIG / "reference8-cia402.yaml").read_text())
    data["robot"] = str(CONFIG / "robots" / "reference8.yaml")
    data["drives"]["force_lag"] = 0.01
    path = tmp_path / "slow.yaml"
    path.write_text(yaml.safe_dump(data))
    check = check_gains(run_cmd.load_checked(str(path)))
    assert main(["analyze", "--config", str(path), "--grid", "2", "--json"]) == 0
    analysed = json.loads(capsys.readouterr().out)["robustness"]["largest_stable_mass"]
    assert analysed == pytest.approx(check.largest_stable_mass, rel=1e-12)
    assert analysed < 53.0  # 53.7 kg at the default 2 ms


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
