"""The first path's kernels compiled ahead (daemon.process.warm_up): a daemon started on
a cold numba cache warms it in a process of its own and marks it; a marked cache, or a
config that is no file, starts nothing.  Each case runs in processes with a cache
directory of its own (NUMBA_CACHE_DIR), so this test process's cache is not moved."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from cdpr.compiled_cache import source_digest
from daemon.process import warm_up
from tests.loopback import free_port
from tests.processes import CONFIG, ROOT, finish, start_daemon


def started(cache: Path, config: Path) -> str:
    """What warm_up.start returns, asked in a process whose cache is `cache`."""
    code = "import sys; from daemon.process import warm_up; print(warm_up.start(sys.argv[1]))"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "CDPRD_WARM_UP": "1"}
    run = subprocess.run(
        [sys.executable, "-c", code, str(config)],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return run.stdout.strip()


def test_a_config_that_is_no_file_starts_nothing(tmp_path: Path) -> None:
    assert warm_up.start(tmp_path / "absent.yaml") is None


def test_cdprd_warm_up_0_starts_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CDPRD_WARM_UP", "0")
    assert warm_up.start(CONFIG) is None


def test_a_marked_cache_starts_nothing(tmp_path: Path) -> None:
    marker = tmp_path / f"cdprd-{source_digest()}" / warm_up.MARKER
    marker.parent.mkdir()
    marker.touch()
    assert started(tmp_path, CONFIG) == "None"
    marker.unlink()
    assert started(tmp_path, CONFIG).startswith("<Popen")  # killed with its parent's exit


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_daemon_on_a_cold_cache_warms_it_for_the_first_path(tmp_path: Path) -> None:
    cache = tmp_path / "numba"
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    marker = cache / f"cdprd-{source_digest()}" / warm_up.MARKER
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "CDPRD_WARM_UP": "1"}
    proc = start_daemon(config, "--sim", env=env)
    try:
        end = time.monotonic() + 500.0  # a cold compile at nice 19: ~20 s on a quiet
        # 2-vCPU host, minutes beside other work (it yields to everything)
        while not marker.exists():
            assert proc.poll() is None, f"the daemon stopped: {finish(proc)}"
            assert time.monotonic() < end, "no warm cache within 500 s"
            time.sleep(0.5)
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    cached = {p.name.split("-")[0] for p in marker.parent.rglob("*.nbi")}
    assert "wrench_margin._normals" in cached, cached  # facet_normals: the path timing's
