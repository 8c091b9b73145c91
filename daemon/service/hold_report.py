"""Whether the brake reached every drive, as the drives themselves say (DESIGN §9).

A brake is frames sent; it holds only once each drive's own answer shows the hold (the
driver sets NodeStatus.held: CiA 402 by SDO in any NMT state, drivers.cia402.hold_check;
ODrive by heartbeat).  The service reports `braked` when it has decided to brake, and
beside it, in status and state, whether every drive confirmed; an event goes out each
time that verdict changes, naming the drives that could not be confirmed and why.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from drivers.base import NodeStatus


def hold_summary(status: Sequence[NodeStatus]) -> dict[str, Any]:
    """{"confirmed": every drive's hold confirmed, "unconfirmed": each drive not (yet)
    confirmed, with the reason where one is known}."""
    unconfirmed = [
        f"drive {k}: {st.hold_problem or 'not confirmed yet'}"
        for k, st in enumerate(status)
        if not st.held
    ]
    return {"confirmed": not unconfirmed, "unconfirmed": unconfirmed}


class HoldReport:
    """Turns the drives' hold verdicts into events, one per change of the whole."""

    def __init__(self) -> None:
        self._last: tuple[bool | None, ...] = ()

    def forget(self) -> None:
        """A new brake: the next verdict is news even if it equals the last one."""
        self._last = ()

    def update(self, status: Sequence[NodeStatus]) -> dict[str, Any] | None:
        """The event for the drives' verdicts if they changed into a whole one: every
        drive confirmed (`brake_confirmed`), or none still being asked and some not
        (`brake_unconfirmed`); None otherwise."""
        verdicts = tuple(st.held for st in status)
        if verdicts == self._last or None in verdicts:
            return None
        self._last = verdicts
        if all(verdicts):
            return {"event": "brake_confirmed"}
        return {"event": "brake_unconfirmed", **hold_summary(status)}
