"""The documentation: the site builds with `mkdocs build --strict` (a broken link or
anchor, a page missing from the navigation fail it), the generated references (CLI,
config, faults) are the ones their code writes, and README, the front door, stays short
and links only to what exists."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from daemon.cli.config_reference import config_reference, key_descriptions, section_of
from daemon.cli.reference import cli_reference
from daemon.config import FileConfig
from daemon.service.fault_guide import GUIDE, fault_reference
from daemon.service.safety import Trigger

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


@pytest.mark.parametrize(
    ("page", "writer", "command"),
    [
        ("config.md", config_reference, "python -m daemon.cli.config_reference"),
        ("faults.md", fault_reference, "python -m daemon.service.fault_guide"),
    ],
)
def test_a_generated_reference_is_the_one_its_code_writes(page, writer, command) -> None:
    text = (ROOT / "docs" / "reference" / page).read_text()
    assert text == writer(), f"docs/reference/{page} is stale: {command} > docs/reference/{page}"


def test_every_config_key_is_described() -> None:
    """Each key of every section has a description (its attribute docstring, comment or
    docstring line): the config reference leaves no key unexplained."""
    missing: list[str] = []
    seen: set[type] = set()

    def walk(path: str, model: type) -> None:
        if model in seen:
            return
        seen.add(model)
        described = key_descriptions(model)
        for name in model.model_fields:
            key = f"{path}.{name}" if path else name
            if name not in described:
                missing.append(f"{key} ({model.__name__})")
            nested = section_of(model, name)
            if nested is not None:
                walk(key, nested)

    walk("", FileConfig)
    assert not missing, f"config keys without a description: {', '.join(missing)}"


def test_every_brake_trigger_has_a_meaning_and_an_action() -> None:
    assert set(GUIDE) == set(Trigger)
    page = fault_reference()
    for trigger in Trigger:
        assert f"## `{trigger.value}`" in page
        assert GUIDE[trigger].meaning and GUIDE[trigger].action
