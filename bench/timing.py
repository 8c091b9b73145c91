"""Shared bits of the benchmarks: the reference robot, per-call timing summaries, a
free zenoh endpoint on loopback, and helper processes beside a real-time daemon."""

from __future__ import annotations

import asyncio
import gc
import json
import os
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REFERENCE8 = Path(__file__).resolve().parent.parent / "config" / "robots" / "reference8.yaml"


def summary_us(samples_ns: np.ndarray) -> dict[str, float]:
    """Median and p99 of per-call times given in nanoseconds, in microseconds."""
    return {
        "median_us": round(float(np.median(samples_ns)) / 1e3, 2),
        "p99_us": round(float(np.percentile(samples_ns, 99)) / 1e3, 2),
    }


def per_call_us(fn: Callable[[int], object], calls: int, warm_up: int = 200) -> dict[str, float]:
    """Call fn(i) for i in range(calls), each timed separately with the collector off,
    after fn(0..warm_up-1) untimed; returns median and p99 in microseconds."""
    for i in range(min(calls, warm_up)):
        fn(i)
    samples = np.empty(calls)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for i in range(calls):
            t0 = clock()
            fn(i)
            samples[i] = clock() - t0
    finally:
        gc.enable()
    return summary_us(samples)


def print_timings(results: dict[str, dict[str, float]]) -> None:
    """One human-readable line per timed item: median and p99 in microseconds."""
    for name, r in results.items():
        print(f"{name:18s} median {r['median_us']:9.2f} us   p99 {r['p99_us']:9.2f} us")


def free_endpoint() -> str:
    """A tcp/127.0.0.1 zenoh endpoint on a port free now (loopback only)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


async def ordinary_child(*args: str) -> dict[str, Any]:
    """`python ARGS` at normal priority (spawned from the daemon's real-time core, a
    child would inherit SCHED_FIFO), the last line of its stdout read as one JSON object
    once it exits."""
    from daemon.process.realtime import spawn_ordinary

    with tempfile.TemporaryFile() as out:
        child = spawn_ordinary([sys.executable, *args], dict(os.environ), stdout=out.fileno())
        while child.poll() is None:
            await asyncio.sleep(0.02)
        out.seek(0)
        text = out.read().decode()
    if child.returncode != 0:
        raise SystemExit(f"{' '.join(args[:2])} failed ({child.returncode}): {text[-500:]}")
    return json.loads(text.splitlines()[-1])  # the last line: a flooder says it floods
