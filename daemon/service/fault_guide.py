"""What each brake trigger means and what to do about it: one entry per
daemon.service.safety.Trigger.  It writes the faults reference page (`python -m
daemon.service.fault_guide > docs/reference/faults.md`; tests/test_docs.py fails while
the page is stale or a trigger has no entry)."""

from __future__ import annotations

from dataclasses import dataclass

from daemon.service.safety import Trigger


@dataclass(frozen=True)
class Guide:
    meaning: str  # what the daemon saw
    action: str  # what a person should check or do


GUIDE: dict[Trigger, Guide] = {
    Trigger.OUT_OF_WORKSPACE: Guide(
        "No cable tensions between each cable's t_min and force_max give the wrench the "
        "controller needs at the measured pose (it is outside the wrench-feasible set W): "
        "the platform is where the cables cannot hold it, or is asked to accelerate harder "
        "than they can pull.",
        "Check the pose the message gives against the workspace (`cdprd analyze`); slow "
        "the trajectory (trajectory.linear_accel); declare or identify the payload "
        "(`cdprd identify-payload`): an undeclared mass changes the wrench.",
    ),
    Trigger.POSE_LIMIT: Guide(
        "The measured pose put a corner of the platform's body outside "
        "safety.workspace_min / workspace_max or across the environment, or tilted it "
        "beyond safety.tilt_max.  The message names the corner and the bound.",
        "If the pose is where the platform really is, something pushed it there "
        "(trajectories are validated with a margin): look for a collision.  If it is not, "
        "the lengths lie: re-home (`cdprd home`).",
    ),
    Trigger.LENGTH_LIMIT: Guide(
        "A cable's measured length left its actuator's length_min..length_max.",
        "Check the cable on its drum and the drive's position (homing offset); re-home.",
    ),
    Trigger.TRACKING_ERROR: Guide(
        "The measured pose was farther from the reference than "
        "safety.tracking_error_position (m) or safety.tracking_error_orientation (rad).",
        "Something resists the motion (a collision, a snagged cable, an undeclared "
        "payload), or the gains are too soft for the trajectory: clear the obstruction, "
        "slow the trajectory, identify the winches (`cdprd tune`).",
    ),
    Trigger.FK_RESIDUAL: Guide(
        "Forward kinematics found no pose that fits the measured lengths within "
        "robot.forward_kinematics.max_residual: the lengths belong to no rigid pose.",
        "A cable slipped or jumped on its drum or pulley, an encoder lost counts, or a "
        "homing offset is wrong: inspect the cables, then re-home (`cdprd home`).",
    ),
    Trigger.IMPLAUSIBLE_FEEDBACK: Guide(
        "A drive's feedback failed the trusted-length checks: a rate above "
        "safety.max_cable_speed, a length that moved faster or otherwise than its rates "
        "say, a length that disagrees with the pose the other cables give by more than "
        "safety.feedback_tolerance, or two different answers to one SYNC (another node "
        "sends that drive's PDOs).  The message names the drive.",
        "Check that drive's encoder and wiring, and that no two nodes share its node id "
        "(`candump can0`).",
    ),
    Trigger.STALE_FEEDBACK: Guide(
        "A drive's feedback missed safety.stale_cycles consecutive cycles (each waits "
        "safety.feedback_deadline of the period for it).",
        "Check the drive's power and CAN wiring and the bus load (`candump -t d can0`); if "
        "many drives miss together, the host: the core's real-time settings (`realtime:`) "
        "and what else runs on its CPU.",
    ),
    Trigger.DRIVE_FAULT: Guide(
        "A drive reports a fault (CiA 402: EMCY or FAULT state; ODrive: an axis error), "
        "left its powered state while it should follow forces (another node changed it, "
        "or it restarted), or could not be enabled.  The message carries its error code.",
        "Look the code up in the drive's manual and clear the cause; a drive that "
        "restarted lost its position zero: re-home.  Then `reset`.",
    ),
    Trigger.HEARTBEAT_LOST: Guide(
        "No heartbeat from a drive for drives.heartbeat_timeout.",
        "Check the drive's power, its CAN wiring and its heartbeat producer time.",
    ),
    Trigger.BUS_ERROR: Guide(
        "More than safety.bus_errors_max CAN error frames or failed sends within a "
        "second, or the controller went bus-off.",
        "Check termination (120 ohm at each end of the bus), the bitrate of every node, "
        "the cabling and its shield (`ip -details -statistics link show can0`).",
    ),
    Trigger.BUS_LOST: Guide(
        "The CAN interface went away (socket closed, interface down, socketcand server "
        "gone).  The daemon brakes, and exits with code 69 after safety.bus_lost_exit s so "
        "that the service manager restarts it.",
        "Check the adapter (`ip link show can0`, its USB connection); systemd's restart "
        "brings the daemon back in IDLE, held.",
    ),
    Trigger.NAN: Guide(
        "A drive reported a length or rate that is not a finite number, or the controller "
        "produced one.",
        "Check that drive's feedback and its scaling in the config; a NaN from the "
        "controller is a bug: report it with the log and the telemetry recording.",
    ),
    Trigger.CONTROLLER_EXCEPTION: Guide(
        "The controller's step raised an exception (named in the message).",
        "A bug: report it with the log line and the telemetry recording.",
    ),
    Trigger.SIGTERM: Guide(
        "The daemon was asked to stop (SIGTERM, `systemctl stop`): it holds and exits.",
        "Nothing: the expected end of a run.",
    ),
    Trigger.COMMAND: Guide(
        "A client asked to brake (the `brake` command).",
        "When it is safe: `reset`, then `enable`.",
    ),
    Trigger.STARTUP: Guide(
        "The drives did not come up at start-up: no answer, a configuration write "
        "refused, or not operational in time.  The message names the drive and the step.",
        "Check power, node ids and bitrate; for CiA 402, the drive's profile against its "
        "EDS (`cdprd check-config FILE`).",
    ),
    Trigger.COMPANION_LOST: Guide(
        "The companion process (zenoh, planning, recording) was gone for "
        "safety.companion_lost s while the robot moved; the core restarts it.",
        "The log says why it died (a crash with its traceback; a companion of other code "
        "after an upgrade: restart the service).  Then `reset` and `enable`.",
    ),
    Trigger.PAYLOAD_LIMIT: Guide(
        "The payload estimate went beyond controller.adaptation's bounds: the platform "
        "carries more, or less, than the adaptation allows.",
        "Check what is on the platform; identify it (`cdprd identify-payload`), or widen "
        "the bounds if the payload is intended.",
    ),
    Trigger.PRETENSION: Guide(
        "Pretension was aborted: a cable did not become taut in pretension.taut_timeout "
        "or wound in more than pretension.max_wind_in, the platform moved more than "
        "pretension.max_motion / max_rotation, or the homed lengths were refused.  The "
        "message names the cable.",
        "Check that cable on its drum and pulley and that the fixture holds the platform; "
        "then `cdprd pretension` again.",
    ),
    Trigger.EXTERNAL_WRENCH: Guide(
        "The external wrench estimate exceeded controller.disturbance_observer's bounds: "
        "something pushes or holds the platform harder than allowed.",
        "Look for a collision or a person holding the platform; clear it, then `reset` "
        "and `enable`.",
    ),
}


def fault_reference() -> str:
    """Markdown: every brake trigger, what it means and what to do."""
    parts = [
        "# Faults reference",
        "",
        "Every reason the daemon brakes, as its log line (`BRAKE [trigger] message`), its "
        "`fault` event and its status name it.  Leaving BRAKED takes the cause gone and "
        "`reset` (see [Safety](../explanation/safety.md)).  Written by `python -m "
        "daemon.service.fault_guide`.",
    ]
    for trigger in Trigger:
        guide = GUIDE[trigger]
        parts += ["", f"## `{trigger.value}`", "", guide.meaning, ""]
        parts.append(f"**What to do:** {guide.action}")
    return "\n".join(parts) + "\n"


if __name__ == "__main__":
    print(fault_reference(), end="")
