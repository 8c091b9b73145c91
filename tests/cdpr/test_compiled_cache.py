"""Numba's cache is keyed by every compiled source (cdpr.compiled_cache): an edit of one
file, or an upgrade, never runs machine code saved from another version of a file it
calls."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

from cdpr.compiled_cache import ROOT, SOURCES, source_digest

PACKAGES = ("cdpr", "daemon", "drivers", "sim_bus", "tuning", "bench")


def test_sources_name_every_file_that_compiles() -> None:
    """Files with kernels, files of plain functions a kernel may call
    (`@register_jitable`), and the files of plain functions a kernel module compiles
    (`name = njit(cache=True)(function)`, function imported from another module)."""
    compiling = set()
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            text = path.read_text()
            if re.search(r"^@(njit|register_jitable)", text, re.M):
                compiling.add(path.relative_to(ROOT).as_posix())
            for name in re.findall(r"= njit\([^)]*\)\((\w+)\)", text):
                module = re.search(rf"^from ([\w.]+) import .*\b{name}\b", text, re.M)
                assert module, f"{path}: where {name} comes from"
                compiling.add(module.group(1).replace(".", "/") + ".py")
    assert "cdpr/so3.py" in compiling  # the wrapped functions are found
    assert compiling == set(SOURCES)


def test_an_edit_of_any_source_moves_the_cache(tmp_path: Path) -> None:
    for name in SOURCES:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / name, tmp_path / name)
    assert source_digest(tmp_path) == source_digest()
    seen = {source_digest(tmp_path)}
    for name in SOURCES:
        with (tmp_path / name).open("a") as stream:
            stream.write("\n# an edit\n")
        seen.add(source_digest(tmp_path))
    assert len(seen) == len(SOURCES) + 1


def test_the_compiled_functions_cache_in_the_keyed_directory(tmp_path: Path) -> None:
    """In a fresh interpreter with NUMBA_CACHE_DIR set (as the systemd unit does): the
    map pass's kernel saves its machine code under cdprd-<digest> there."""
    script = (
        "import numpy as np\n"
        "from tuning.workspace_map import _cables\n"
        "print(_cables._cache._cache_path)\n"
    )
    env = {"NUMBA_CACHE_DIR": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    path = Path(done.stdout.strip())
    assert path.is_relative_to(tmp_path / f"cdprd-{source_digest()}"), path
