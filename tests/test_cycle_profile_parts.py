"""bench/cycle_profile.py times a cycle's parts by wrapping the core's methods by name
from outside (nothing in the service times itself): every part it names must be a
method of the core it profiles, or the bench fails after its minute of set-up (it did
twice, after a rename and after a removal)."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))  # the bench imports its sibling modules by name

from cycle_profile import PARTS  # noqa: E402
from loop import rate_config  # noqa: E402

from tests.daemon_stack import Stack  # noqa: E402


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0])
def test_every_part_the_profile_wraps_is_a_method_of_the_core(
    rate_hz: float, tmp_path: Path
) -> None:
    """On the core as the bench profiles it: started (its timers exist from then)."""
    config, _ = rate_config("cia402", rate_hz, tmp_path)

    async def missing() -> list[str]:
        async with Stack(config) as stack:
            service, absent = stack.service, []
            for part, _, where in PARTS:
                owner, attribute = where(service)
                if owner is not None and not callable(getattr(owner, attribute, None)):
                    absent.append(f"{part}: {type(owner).__name__}.{attribute}")
            return absent

    absent = asyncio.run(missing())
    assert not absent, f"cycle_profile wraps what the core does not have: {absent}"
