"""The controller's online estimates as the daemon's commands and state show them: the
payload estimate (cdpr.payload; the `payload` command freezes, unfreezes or sets it) and
the external wrench observer (cdpr.wrench_observer; the `observer` command holds it out
of the loop or lets it back in).  Each command's reply is the estimate's published state.
"""

from __future__ import annotations

from typing import Any

from cdpr.controller import ParallelController
from daemon.service.api import CommandError


def payload_command(controller: ParallelController, args: dict[str, Any]) -> dict[str, Any]:
    """Freeze or unfreeze the payload estimate, or set it (identify-payload's, applied;
    within controller.adaptation's limits); the reply is the estimate."""
    estimate = controller.payload
    if estimate is None:
        raise CommandError(
            "invalid_state", "the payload estimate is off (controller.adaptation.enabled)"
        )
    if "mass" in args:
        try:
            controller.set_payload(args["mass"], args["center_of_mass"])
        except ValueError as exc:
            raise CommandError("rejected", str(exc)) from None
    if "frozen" in args:
        estimate.frozen = args["frozen"]
    state = payload_state(controller)
    assert state is not None
    return state


def payload_state(controller: ParallelController) -> dict[str, Any] | None:
    """The payload estimate as published (None when it is off)."""
    estimate = controller.payload
    if estimate is None:
        return None
    return {
        "mass": estimate.mass,
        "center_of_mass": list(estimate.center_of_mass),
        # about the centre of mass, platform frame (the file's unless adaptation.inertia)
        "inertia": estimate.platform.inertia.tolist(),
        "frozen": estimate.frozen,
    }


def observer_command(controller: ParallelController, args: dict[str, Any]) -> dict[str, Any]:
    """Hold the external wrench observer out of the loop, or let it back in (args "held";
    ParallelController.hold_observer: `cdprd calibrate` flies with it held); the reply is
    its state."""
    if controller.observer is None:
        raise CommandError(
            "invalid_state",
            "the external wrench observer is off (controller.disturbance_observer.enabled)",
        )
    if "held" in args:
        controller.hold_observer(args["held"])
    state = observer_state(controller)
    assert state is not None
    return state


def observer_state(controller: ParallelController) -> dict[str, Any] | None:
    """The external wrench observer as published (None when it is off)."""
    observer = controller.observer
    if observer is None:
        return None
    return {"held": controller.observer_held, "estimate": observer.estimate.tolist()}
