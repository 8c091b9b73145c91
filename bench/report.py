"""The performance page (docs/explanation/performance.md), written from the benches'
JSON and never by hand.

    python bench/report.py --run [--runs 3] [--only model,loop]  # run, keep their JSON
    python bench/report.py                                       # write the page

`--run` runs each bench of BENCHES `--runs` times as the page shows its command, and
keeps what each run printed (one JSON object) in bench/results/<name>.json with the
machine, the date and the commit.  Without `--run` the page is written from those
files: per bench its command, its docstring's first paragraph, the machine and commit,
and every number it printed, as the median over the runs with their range.  The
medians are of what each run printed (most figures are themselves medians or
percentiles over thousands of calls or cycles).  tests/test_docs.py fails when the page
is not what the stored results give.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
PAGE = ROOT / "docs" / "explanation" / "performance.md"


@dataclass(frozen=True)
class Bench:
    """A bench as the page runs it: bench/<name>.py with `options` (and --json)."""

    name: str
    options: tuple[str, ...] = ()

    @property
    def command(self) -> list[str]:
        return ["python", f"bench/{self.name}.py", "--json", *self.options]

    def summary(self) -> str:
        """The first paragraph of the bench's docstring, on one line."""
        tree = ast.parse((ROOT / "bench" / f"{self.name}.py").read_text())
        doc = ast.get_docstring(tree) or ""
        return " ".join(doc.split("\n\n")[0].split())


BENCHES = (
    Bench("model"),
    Bench("tension"),
    Bench("trajectory"),
    Bench("controller", ("--skip-tracking",)),
    Bench("loop", ("--seconds", "6")),
    Bench("io_floor"),
    Bench("simulator"),
    Bench("zenoh_io"),
    Bench("planning", ("--no-ratios", "--runs", "5")),
    Bench("workspace"),
)


def machine() -> dict[str, Any]:
    """What the figures are for: CPU model, CPUs, kernel, Python."""
    model = platform.processor() or "unknown CPU"
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    return {
        "cpu": model,
        "cpus": os.cpu_count(),
        "kernel": platform.release(),
        "python": platform.python_version(),
    }


def commit() -> str:
    """The checked-out commit (short), with "+changes" when the tree differs from it."""
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=ROOT).returncode != 0
    return f"{head}+changes" if dirty else head


def run(bench: Bench, runs: int) -> dict[str, Any]:
    """`runs` runs of `bench`: each one's JSON (its last line of output)."""
    outputs, loads = [], []
    for k in range(runs):
        loads.append(round(os.getloadavg()[0], 2))  # other work on the host, if any
        print(f"{' '.join(bench.command)}  ({k + 1}/{runs})", file=sys.stderr, flush=True)
        argv = [sys.executable, *bench.command[1:]]
        done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, check=False)
        lines = done.stdout.strip().splitlines()
        if done.returncode != 0 or not lines:
            raise SystemExit(f"{bench.name} failed ({done.returncode}): {done.stderr[-2000:]}")
        outputs.append(json.loads(lines[-1]))
    return {
        "command": bench.command,
        "date": datetime.date.today().isoformat(),
        "commit": commit(),
        "machine": machine(),
        "load_average": loads,
        "runs": outputs,
    }


def leaves(data: Any, prefix: str = "") -> dict[str, Any]:
    """Every number and text in a bench's JSON by its dotted path (list items by index)."""
    if not isinstance(data, dict | list):
        return {} if data is None or isinstance(data, bool) else {prefix: data}
    items = data.items() if isinstance(data, dict) else enumerate(data)
    out: dict[str, Any] = {}
    for key, value in items:
        out.update(leaves(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def figure(x: float) -> str:
    """A number as the page prints it: four significant digits, no exponent for the
    sizes benches print."""
    if x == int(x) and abs(x) < 1e9:
        return str(int(x))
    return f"{x:.4g}" if 1e-3 <= abs(x) < 1e6 else f"{x:.3e}"


def section(bench: Bench, stored: dict[str, Any]) -> list[str]:
    """The page's section of one bench: what it measures, how, and its medians."""
    runs = stored["runs"]
    m = stored["machine"]
    lines = [
        f"## {bench.name}",
        "",
        bench.summary(),
        "",
        f"`{' '.join(stored['command'])}`: {len(runs)} runs on {stored['date']}, commit "
        f"{stored['commit']}; {m['cpu']}, {m['cpus']} CPUs, Linux {m['kernel']}, "
        f"Python {m['python']}.",
        "",
    ]
    if "load_average" in stored:
        loads = stored["load_average"]
        lines += [
            f"The host's 1-minute load average as each run began: "
            f"{', '.join(figure(x) for x in loads)} (other work on it slows every figure).",
            "",
        ]
    lines += [
        "| figure | median | range |",
        "| --- | --- | --- |",
    ]
    per_run = [leaves(r) for r in runs]
    texts: dict[str, list[str]] = {}  # what the runs said (a fault, a setting), by key
    for key in dict.fromkeys(k for r in per_run for k in r):
        values = [r[key] for r in per_run if key in r]
        if all(isinstance(v, int | float) for v in values):
            low, high = figure(min(values)), figure(max(values))
            spread = low if low == high else f"{low} .. {high}"
            lines.append(f"| {key} | {figure(statistics.median(values))} | {spread} |")
        else:
            texts[key] = [str(v) for v in values if v != ""]
    for key, said in texts.items():
        if said:
            counted = ", ".join(
                f"{v!r} ({said.count(v)} of {len(runs)})" for v in dict.fromkeys(said)
            )
            lines += ["", f"{key}: {counted}"]
    return [*lines, ""]


def page(results: Path = RESULTS) -> str:
    """The performance page from the stored results (a bench without any is listed as
    not measured)."""
    lines = [
        "# Performance",
        "",
        "Written by `python bench/report.py` from the benches' JSON in `bench/results/`, "
        "never by hand: `python bench/report.py --run --runs 3` measures again (on a quiet "
        "host), `python bench/report.py` writes this page. Each figure is the median over "
        "the runs of what each run printed, with its range; what a figure means is in its "
        "bench's docstring. Nothing here is hard real time: the figures are for the "
        "machine named.",
        "",
    ]
    missing = []
    for bench in BENCHES:
        path = results / f"{bench.name}.json"
        if path.exists():
            lines += section(bench, json.loads(path.read_text()))
        else:
            missing.append(f"`{' '.join(bench.command)}`")
    if missing:
        lines += ["## Not measured yet", "", ", ".join(missing), ""]
    return "\n".join(lines).rstrip() + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="run the benches first")
    parser.add_argument("--runs", type=int, default=3, help="runs of each bench")
    parser.add_argument("--only", default="", help="comma-separated bench names")
    args = parser.parse_args()
    chosen = [b for b in BENCHES if not args.only or b.name in args.only.split(",")]
    if args.only and len(chosen) != len(args.only.split(",")):
        known = ", ".join(b.name for b in BENCHES)
        raise SystemExit(f"--only: unknown bench in {args.only!r}; known: {known}")
    if args.run:
        RESULTS.mkdir(exist_ok=True)
        for bench in chosen:
            stored = run(bench, args.runs)
            (RESULTS / f"{bench.name}.json").write_text(json.dumps(stored, indent=1) + "\n")
    PAGE.write_text(page())
    print(f"wrote {PAGE.relative_to(ROOT)}", file=sys.stderr)


if __name__ == "__main__":
    main()
