"""bench/report.py: the performance page is what the stored bench results give, never
written by hand, and its figures are the medians of what the runs printed."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
_SPEC = importlib.util.spec_from_file_location("bench_report", ROOT / "bench" / "report.py")
assert _SPEC is not None and _SPEC.loader is not None
report = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = report  # its dataclass looks itself up there
_SPEC.loader.exec_module(report)


def test_the_performance_page_is_the_one_the_stored_results_give() -> None:
    assert report.PAGE.read_text() == report.page(), (
        "docs/explanation/performance.md is stale: python bench/report.py"
    )


def test_a_figure_is_the_median_of_the_runs_with_their_range(tmp_path: Path) -> None:
    def printed(us: float, count: int) -> dict:
        fault = "" if us < 30.0 else "drive_fault: heartbeat"
        return {
            "step": {"median_us": us, "count": count},
            "ok": True,
            "fault": fault,
            "rates": [1.5, us],
        }

    stored = {
        "command": ["python", "bench/model.py", "--json"],
        "date": "2026-12-04",
        "commit": "abc1234",
        "machine": {"cpu": "Some CPU", "cpus": 2, "kernel": "6.1", "python": "3.11.7"},
        "load_average": [0.1, 2.5, 0.0],
        "runs": [printed(30.0, 7), printed(10.0, 7), printed(20.5, 7)],
    }
    (tmp_path / "model.json").write_text(json.dumps(stored))
    text = report.page(tmp_path)
    assert "| step.median_us | 20.5 | 10 .. 30 |" in text
    assert "| step.count | 7 | 7 |" in text
    assert "| rates.0 | 1.5 | 1.5 |" in text and "| rates.1 | 20.5 | 10 .. 30 |" in text
    assert "| ok " not in text and "| fault " not in text  # booleans and text are no figures
    assert "fault: 'drive_fault: heartbeat' (1 of 3)" in text  # what the runs said
    assert "`python bench/model.py --json`: 3 runs on 2026-12-04, commit abc1234" in text
    assert report.Bench("model").summary() in text
    assert "load average as each run began: 0.1, 2.5, 0 (other work" in text
    # the benches without results are named with their commands
    assert "## Not measured yet" in text and "`python bench/loop.py --json --seconds 6`" in text
