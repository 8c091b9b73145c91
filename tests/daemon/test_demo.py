"""`cdprd demo`, the README's main command: simulator + daemon + zenoh client in one
process; the run must end holding, with sub-millimetre tracking of the simulated
platform and no slack cable."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(120)
def test_demo_flies_the_figure_eight_and_ends_holding(tmp_path: Path) -> None:
    plot = tmp_path / "demo.png"
    run = subprocess.run(
        [sys.executable, "-m", "daemon.cli", "demo", "--plot", str(plot)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=100,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    out = run.stdout
    assert "trajectory accepted over zenoh" in out
    rms = float(re.search(r"RMS ([0-9.]+) mm", out).group(1))
    assert rms < 1.0, out
    assert "slack events 0" in out and "final state: hold" in out
    assert plot.stat().st_size > 10_000
    drawing = tmp_path / "demo-3d.png"
    assert f"3-D view at the largest tension written to {drawing}" in out
    data = drawing.read_bytes()
    assert data.startswith(b"\x89PNG") and len(data) > 10_000
