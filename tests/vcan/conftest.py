"""Decide where ``vcan``-marked tests run: natively, inside UML, or nowhere (skip).

* A usable ``vcan0`` here (natively, or because this *is* the UML guest):
  the vcan tests run as they are, and ``test_vcan_suite_in_uml`` skips.
* No ``vcan0`` but a bootable UML: the vcan tests skip here, and
  ``test_vcan_suite_in_uml`` re-runs exactly the selected ones in one UML
  guest, failing with the guest's report if any of them failed there.
* Neither: everything skips, saying what to install.
"""

from __future__ import annotations

import os

import pytest
import uml
from guest_suite import GUEST_NODEIDS, GUEST_SUMMARY, SUITE_TEST, nowhere_reason


def skip_reason() -> str | None:
    """Why vcan tests cannot run in this process, or ``None`` if they can."""
    native = uml.native_vcan_reason()
    if native is None or os.environ.get(uml.GUEST_ENV):
        return None  # in the guest, a broken vcan0 must fail the tests, not skip them
    return nowhere_reason(native) or f"no {uml.CHANNEL} here ({native}); run via UML ({SUITE_TEST})"


@pytest.hookimpl(trylast=True)  # after `-m`/`-k` have deselected items
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    vcan_items = [
        item for item in items if item.get_closest_marker("vcan") and item.name != SUITE_TEST
    ]
    config.stash[GUEST_NODEIDS] = [item.nodeid for item in vcan_items]
    reason = skip_reason() if vcan_items else None
    if reason:
        for item in vcan_items:
            item.add_marker(pytest.mark.skip(reason=reason))


def pytest_terminal_summary(
    terminalreporter: pytest.TerminalReporter, config: pytest.Config
) -> None:
    summary = config.stash.get(GUEST_SUMMARY, None)
    if summary:
        terminalreporter.write_sep("-", "vcan tests in UML guest")
        terminalreporter.write_line(summary)
