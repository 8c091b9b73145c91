"""daemon.process.heap: with glibc set to reuse freed large blocks, numpy arrays of 1-16
MB made and dropped again (the path timing's pattern) fault in no new pages; without
it, every round faults in megabytes.  Each case in a process of its own: the setting is
the process's for good."""

from __future__ import annotations

import subprocess
import sys

import pytest

ROUNDS = (
    "import resource, sys\n"
    "import numpy as np\n"
    "if sys.argv[1] == 'on':\n"
    "    from daemon.process.heap import reuse_freed_memory\n"
    "    assert reuse_freed_memory()\n"
    "def once():\n"
    "    arrays = [np.ones(n << 17) for n in (1, 2, 4, 8, 16)]\n"
    "    del arrays\n"
    "once()\n"
    "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
    "for _ in range(4):\n"
    "    once()\n"
    "print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 4)\n"
)


def _faults_per_round(setting: str) -> float:
    out = subprocess.run(
        [sys.executable, "-c", ROUNDS, setting], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return float(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_freed_large_blocks_are_reused_without_page_faults() -> None:
    assert _faults_per_round("off") > 100  # 4 kB pages of 31 MB written: thousands at most
    assert _faults_per_round("on") < 10
