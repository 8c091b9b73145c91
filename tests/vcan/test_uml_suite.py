"""The host's view of the vcan tests when this kernel has no vcan0: run them in UML."""

from __future__ import annotations

import os
from pathlib import Path

import guest_suite
import pytest
import uml

pytestmark = [pytest.mark.vcan, pytest.mark.slow]


@pytest.mark.timeout(uml.DEFAULT_TIMEOUT + 60)  # the guest run has its own, shorter, bound
def test_vcan_suite_in_uml(request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """Boot one UML guest, run every selected vcan test there, and pass only if all pass."""
    native = uml.native_vcan_reason()
    if native is None:
        pytest.skip(f"{uml.CHANNEL} is usable here, so the vcan tests run directly")
    if os.environ.get(uml.GUEST_ENV):
        pytest.fail(f"inside the UML guest, yet {native}")
    nowhere = guest_suite.nowhere_reason(native)
    if nowhere:
        pytest.skip(nowhere)
    nodeids = request.config.stash.get(guest_suite.GUEST_NODEIDS, [])
    if not nodeids:
        pytest.skip("no other vcan test is selected")

    suite = guest_suite.run_suite(request.config, nodeids, tmp_path)

    counted = len(suite.passed) + len(suite.failed) + len(suite.skipped)
    if suite.run.exit_code != 0 or suite.failed or not suite.passed or counted != len(nodeids):
        failures = "".join(f"\n  FAILED {name}: {why}" for name, why in suite.failed.items())
        pytest.fail(
            f"UML guest ran {counted} of {len(nodeids)} vcan tests: {suite.summary()}{failures}\n"
            "(the guest's whole output is in this test's captured stdout)",
            pytrace=False,
        )
