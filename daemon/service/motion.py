"""One owner per motion (DESIGN §19): the client whose flight or procedure moves the robot.

A motion is a flight (a trajectory or a goto: it runs from the moment the core takes it
until its end time) or a procedure (identify_payload, home, pretension: it runs until
its command ends).  While one runs, a request for another is refused ("not_owner",
naming what runs and who started it) unless

- it says `preempt: true`, or
- it is a flight from the client whose flight runs: a planner streaming its path
  replaces its own trajectory, as it always could (the reference stays continuous).

A procedure is replaced only by a request that preempts, even one of its own client's.
The client a preempting request (or a `hold`, which stops any motion) takes the motion
from gets the event `motion_preempted`, naming what it ran, what replaced it and who
asked; a procedure so replaced stops ("preempted") at its next step.  A brake, a disable
or any other stop of the robot ends a flight too.

Clients are who they say they are (the request's `client`, ANONYMOUS without one): this
keeps one client's motion from being replaced by another's by accident, it is no access
control (zenoh's is: docs/reference/zenoh-api.md).  The registry lives beside the planner in the
companion process, never in the control cycle.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from daemon.service.api import MOVING, Claim, CommandError

FLIGHTS = ("trajectory", "goto")
PROCEDURES = ("identify_payload", "home", "pretension")
EventSink = Callable[[dict[str, Any]], None]


@dataclass(eq=False)
class Motion:
    """One motion and its claim; `end`: the core time a flight ends (inf until the core
    took it), None for a procedure; `replaced_by`: (what, client) once replaced."""

    what: str
    claim: Claim
    end: float | None
    previous: Motion | None = None
    replaced_by: tuple[str, str] | None = field(default=None)

    def describe(self) -> dict[str, Any]:
        """What runs, who started it (and a trajectory's id): for the state and events."""
        described = {"what": self.what, "client": self.claim.client}
        return described if self.claim.id is None else {**described, "id": self.claim.id}


class Motions:
    """The motion running, if any; `now` is the core's clock, `emit` takes the events."""

    def __init__(self, now: Callable[[], float], emit: EventSink) -> None:
        self._now = now
        self._emit = emit
        self._motion: Motion | None = None

    def running(self) -> Motion | None:
        """The motion running now (a flight past its end has ended)."""
        motion = self._motion
        if motion is not None and motion.end is not None and self._now() >= motion.end:
            self._motion = motion = None
        return motion

    def check(self, what: str, claim: Claim) -> None:
        """Refuse (CommandError "not_owner") a motion `what` that `claim` may not start
        now: another one runs, and neither rule above lets it replace that."""
        running = self.running()
        if running is None or claim.preempt:
            return
        if what in FLIGHTS and running.what in FLIGHTS and running.claim.client == claim.client:
            return
        whose = "yours" if running.claim.client == claim.client else "another client's"
        raise CommandError(
            "not_owner",
            f"{what} refused: {_named(running)} runs ({whose}); send preempt: true to replace it",
            running=running.describe(),
        )

    def take(self, what: str, claim: Claim) -> Motion:
        """`what` runs now for `claim` (check()ed again here: no await between the check
        and the take); a flight's end is unknown until commit()."""
        self.check(what, claim)
        motion = Motion(what, claim, None if what in PROCEDURES else math.inf, self.running())
        self._motion = motion
        if what in PROCEDURES:
            self.commit(motion, None)
        return motion

    def commit(self, motion: Motion, end: float | None) -> None:
        """The core took `motion` (a flight, ending at core time `end`): the motion it
        replaced is over, and its client told if it was another's."""
        motion.end = end
        previous, motion.previous = motion.previous, None
        if previous is not None and self._motion is motion:
            self._replaced(previous, motion.what, motion.claim.client)

    def restore(self, motion: Motion) -> None:
        """The core did not take the flight `motion`: what it was to replace runs on."""
        if self._motion is motion:
            self._motion = motion.previous
        motion.previous = None

    def finish(self, motion: Motion) -> None:
        """A procedure's command ended."""
        if self._motion is motion:
            self._motion = None

    def stopped(self, claim: Claim) -> None:
        """A hold from `claim` stopped whatever ran."""
        running, self._motion = self.running(), None
        if running is not None:
            self._replaced(running, "hold", claim.client)

    def owns(self, motion: Motion) -> None:
        """CommandError "preempted" unless the procedure `motion` still runs (also while
        a flight that would replace it waits for the core to take it)."""
        pending = self._motion
        while pending is not None:
            if pending is motion:
                return
            pending = pending.previous
        if motion.replaced_by is None:
            reason = f"{motion.what} stopped: the robot stopped"
        else:
            what, client = motion.replaced_by
            reason = f"{motion.what} stopped: replaced by {what} from {client}"
        raise CommandError("preempted", reason)

    def on_event(self, event: dict[str, Any]) -> None:
        """The core's events: a robot that stops moving (brake, disable) ends a flight."""
        motion = self._motion
        if motion is not None and motion.what in FLIGHTS and event.get("state") not in MOVING:
            self._motion = None

    def _replaced(self, motion: Motion, what: str, client: str) -> None:
        motion.replaced_by = (what, client)
        if client != motion.claim.client:
            by = {"what": what, "client": client}
            self._emit({"event": "motion_preempted", **motion.describe(), "by": by})


def _named(motion: Motion) -> str:
    """E.g. "trajectory 'plan-42' from alice@host:12", "identify_payload from bob"."""
    ident = "" if motion.claim.id is None else f" {motion.claim.id!r}"
    return f"{motion.what}{ident} from {motion.claim.client}"
