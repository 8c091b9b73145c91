"""The documentation: the site builds with `mkdocs build --strict` (a broken link or
anchor, a page missing from the navigation fail it), the CLI reference is the one the
parser writes, and README, the front door, stays short and links only to what exists."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from daemon.cli.reference import cli_reference

ROOT = Path(__file__).resolve().parent.parent
README_LINES = 200


def test_the_site_builds_strict(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "site" / "index.html").is_file()


def test_readme_is_a_short_front_door_whose_links_resolve() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_LINES
    targets = re.findall(r"\]\(([^)#\s]+)[^)]*\)", text)
    local = [t for t in targets if "://" not in t]
    assert local, "README links to the docs"
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, f"README links to what does not exist: {missing}"


def test_the_cli_reference_is_the_one_the_parser_writes() -> None:
    page = (ROOT / "docs" / "reference" / "cli.md").read_text()
    assert page == cli_reference(), (
        "docs/reference/cli.md is stale: python -m daemon.cli.reference > docs/reference/cli.md"
    )
    assert "## cdprd demo" in page and "## cdprd send" in page
