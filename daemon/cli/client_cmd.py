"""The `cdprd` client commands: send a trajectory, run a command, print the daemon's reply.

    cdprd send FILE [--start now|UNIX_TIME] [--id ID] [--preempt] [--wait]  (YAML or JSON)
    cdprd send FILE --path | --gcode --config CFG [--blend M]  (a path the daemon times)
    cdprd status | enable | disable | hold | reset
    cdprd brake [--reason TEXT]
    cdprd goto x y z [qw qx qy qz] [--preempt] [--wait]
    cdprd identify-payload [--apply] [--preempt]
    cdprd payload [--freeze [--lease S] | --unfreeze] [--lease-id ID]
    cdprd observer [--hold [--lease S] | --release] [--lease-id ID]  (the wrench observer)
    cdprd home [--pose NAME] [--preempt]  (the platform resting at the robot file's pose)
    cdprd pretension [--pose NAME] [--preempt]  (from slack cables, on a fixture there)
    common options: --prefix cdpr/<robot>  --connect tcp/127.0.0.1:7448  --timeout S
                    --zenoh-config FILE (raw zenoh keys, e.g. TLS certificates)
                    --client NAME (who asks, in the daemon's events; default user@host:pid)
                    --json (the daemon's reply as one JSON object on stdout; a refusal
                    as {"error": {"code", "reason", ...}})

Without --json the reply is printed as YAML.  send --wait and goto --wait follow the
accepted motion through the published state until it ends (exit 0 holding its last
pose, 1 if it braked or was stopped); they, home, pretension and identify-payload show
a progress line on stderr (a terminal, or --progress): the phase, the time elapsed and,
where the reply says how long the motion lasts, an ETA.

--preempt replaces a motion another client runs (refused otherwise, naming it); a lease
taken with --lease prints its lease_id, which --lease-id gives to renew or release it.

Exit codes: 0 accepted / done, 1 the daemon refused (the reason is printed) or the
motion waited for braked or stopped, 2 usage (bad arguments, unreadable file, several
daemons and no --prefix), 3 no daemon reachable.
"""

from __future__ import annotations

import argparse
import math
import queue
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from cdpr.description import ConfigError
from cdpr.trajectory import TrajectoryError
from daemon.cli.exit_codes import EXIT_FAILED, EXIT_OK, EXIT_UNREACHABLE, EXIT_USAGE
from daemon.cli.input_files import UsageError, read_mapping, read_path
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.progress import ProgressLine, add_progress_flag, progress_line
from daemon.interface.client import (
    CONNECT_ENV,
    DEFAULT_CONNECT,
    DEFAULT_TIMEOUT,
    CdprClient,
    ClientError,
    RequestError,
    UnreachableError,
    default_connect,
)

LEASE_HELP = (
    "with --freeze/--hold: let go after S seconds unless the same command comes again "
    "(docs/reference/zenoh-api.md, leases); the reply's lease_id renews or ends it"
)
LEASE_ID_HELP = "the lease_id the hold on a lease replied: needed to renew or release it"
PREEMPT_HELP = "replace a motion another client runs (refused otherwise, naming it)"
WAIT_HELP = (
    "wait until the motion ends, following the daemon's state (exit 1 if it braked or "
    "was stopped); a progress line with its ETA on stderr"
)
STOPPED_GRACE = 0.5  # s: a motion no longer ours this long before its end was stopped
IDENTIFY_TIMEOUT = 120.0  # s: identify-payload moves through five poses
PRETENSION_TIMEOUT = 120.0  # s: winding in (up to pretension.taut_timeout), ramp, settle
_SIMPLE = {
    "status": "print the daemon's safety state",
    "enable": "enable the drives (IDLE -> ENABLED, holding the current pose)",
    "disable": "stop moving and disable the drives (brakes on)",
    "hold": "stop smoothly and hold the pose",
    "reset": "leave BRAKED once the fault is gone",
}


Action = Callable[[CdprClient, ProgressLine], Any]
Watch = Callable[[CdprClient, ProgressLine], list[zenoh.Subscriber]]


class MotionInterruptedError(ClientError):
    """A motion waited for did not end as planned: `code` (braked, stopped), `reason`,
    and `details` (the accepted reply, the last state's safety state, fault, motion)."""

    def __init__(self, code: str, reason: str, details: dict[str, Any]) -> None:
        self.code, self.reason, self.details = code, reason, details
        super().__init__(reason)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register the client commands; each sets `run` (args -> exit code)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--prefix",
        help="key prefix of the daemon, e.g. cdpr/reference8 "
        "(default: the only daemon answering on cdpr/*/alive)",
    )
    common.add_argument(
        "--connect",
        help="zenoh endpoint of the daemon or router "
        f"(default ${CONNECT_ENV}, else {DEFAULT_CONNECT})",
    )
    common.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="YAML or JSON file of raw zenoh keys for the session, e.g. transport.link.tls "
        "for a TLS endpoint (docs/reference/zenoh-api.md)",
    )
    common.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT,
        help=f"seconds to wait for the reply (default {DEFAULT_TIMEOUT:g})",
    )
    common.add_argument(
        "--client",
        metavar="NAME",
        help="who asks, as the daemon records it in its events (default user@host:pid)",
    )
    add_json_flag(common)
    send = subparsers.add_parser(
        "send",
        parents=[common],
        help="send a trajectory file (YAML or JSON) and await the verdict",
    )
    send.add_argument("file", help="trajectory in the form of docs/reference/zenoh-api.md")
    kind = send.add_mutually_exclusive_group()
    kind.add_argument(
        "--path", action="store_true", help="FILE is a path (docs/guide/paths.md), timed there"
    )
    kind.add_argument(
        "--gcode",
        action="store_true",
        help="FILE is G-code, from the robot's home as `cdprd plan` reads it (needs --config)",
    )
    send.add_argument("--config", help="--gcode: the daemon's config (the robot's home, limits)")
    send.add_argument("--blend", type=float, default=0.0, help="--gcode: corner blend radius, m")
    send.add_argument("--start", default="now", help='"now" (default) or a unix time in seconds')
    send.add_argument("--id", help="request id echoed in the reply and the events")
    send.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    send.add_argument("--wait", action="store_true", help=WAIT_HELP)
    add_progress_flag(send)
    send.set_defaults(run=_runner("send", _prepare_send))
    for name, text in _SIMPLE.items():
        sub = subparsers.add_parser(name, parents=[common], help=text)
        sub.set_defaults(run=_runner(name, _prepare_request(name)))
    brake = subparsers.add_parser(
        "brake", parents=[common], help="brake now (cable lengths frozen)"
    )
    brake.add_argument("--reason", help="why, recorded with the fault")
    brake.set_defaults(run=_runner("brake", lambda args: lambda c, _: c.brake(args.reason)))
    goto = subparsers.add_parser("goto", parents=[common], help="move smoothly to a pose")
    goto.add_argument(
        "pose", nargs="+", metavar="x y z [qw qx qy qz]", help="position (m), quaternion"
    )
    goto.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    goto.add_argument("--wait", action="store_true", help=WAIT_HELP)
    add_progress_flag(goto)
    goto.set_defaults(run=_runner("goto", _prepare_goto))
    identify = subparsers.add_parser(
        "identify-payload",
        parents=[common],
        help="hold a few poses, estimate the platform's mass and centre of mass statically",
    )
    identify.add_argument(
        "--apply", action="store_true", help="use the estimate in the controller's model"
    )
    identify.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    add_progress_flag(identify)
    identify.set_defaults(
        run=_runner(
            "identify_payload",
            lambda a: lambda c, _: c.identify_payload(a.apply, a.preempt),
            _watch_identify,
        ),
        timeout=IDENTIFY_TIMEOUT,
    )
    payload = subparsers.add_parser(
        "payload", parents=[common], help="print, freeze or unfreeze the payload estimate"
    )
    frozen = payload.add_mutually_exclusive_group()
    frozen.add_argument("--freeze", dest="frozen", action="store_const", const=True)
    frozen.add_argument("--unfreeze", dest="frozen", action="store_const", const=False)
    payload.add_argument("--lease", type=float, metavar="S", help=LEASE_HELP)
    payload.add_argument("--lease-id", metavar="ID", help=LEASE_ID_HELP)
    payload.set_defaults(
        run=_runner(
            "payload",
            lambda a: lambda c, _: c.payload(a.frozen, lease=a.lease, lease_id=a.lease_id),
        )
    )
    observer = subparsers.add_parser(
        "observer", parents=[common],
        help="print the external wrench observer, hold it out of the loop or let it back in",
    )  # fmt: skip
    held = observer.add_mutually_exclusive_group()
    held.add_argument("--hold", dest="held", action="store_const", const=True)
    held.add_argument("--release", dest="held", action="store_const", const=False)
    observer.add_argument("--lease", type=float, metavar="S", help=LEASE_HELP)
    observer.add_argument("--lease-id", metavar="ID", help=LEASE_ID_HELP)
    observer.set_defaults(
        run=_runner("observer", lambda a: lambda c, _: c.observer(a.held, a.lease, a.lease_id))
    )
    home = subparsers.add_parser(
        "home",
        parents=[common],
        help="set every cable's length offset with the platform resting at a known pose",
    )
    home.add_argument(
        "--pose", help="the robot file's pose (poses:) it rests at (default: the home pose)"
    )
    home.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    add_progress_flag(home)
    home.set_defaults(
        run=_runner("home", lambda a: lambda c, _: c.home(a.pose, a.preempt), _watch_state)
    )
    pretension = subparsers.add_parser(
        "pretension",
        parents=[common],
        help="wind slack cables in, tension them without moving the platform, close the loop",
    )
    pretension.add_argument(
        "--pose", help="the robot file's pose (poses:) of the fixture it rests on (default home)"
    )
    pretension.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    add_progress_flag(pretension)
    pretension.set_defaults(
        run=_runner(
            "pretension", lambda a: lambda c, _: c.pretension(a.pose, a.preempt), _watch_state
        ),
        timeout=PRETENSION_TIMEOUT,
    )


def _runner(
    name: str, prepare: Callable[[argparse.Namespace], Action], watch: Watch | None = None
) -> Callable[[argparse.Namespace], int]:
    """args -> exit code: check the arguments (`prepare`, before any network), connect,
    run the action (`watch` feeding the progress line from the daemon's state and events
    meanwhile), print the result or the reason (daemon.cli.output)."""

    def run(args: argparse.Namespace) -> int:
        as_json = args.json
        try:
            if not (args.timeout > 0 and math.isfinite(args.timeout)):
                raise UsageError(f"--timeout must be a positive number of seconds: {args.timeout}")
            action = prepare(args)
            raw = None if args.zenoh_config is None else read_mapping(args.zenoh_config)
            with (
                CdprClient(
                    args.prefix,
                    args.connect or default_connect(),
                    timeout=args.timeout,
                    zenoh_config=raw,
                    name=args.client,
                ) as client,
                progress_line(name.replace("_", "-"), getattr(args, "progress", False)) as line,
            ):
                watching = [] if watch is None or not line.enabled else watch(client, line)
                try:
                    result = action(client, line)
                finally:
                    for subscriber in watching:
                        subscriber.undeclare()
        except UsageError as exc:
            print_error("usage", str(exc), as_json, prefix="usage error")
            return EXIT_USAGE
        except UnreachableError as exc:
            print_error("unreachable", f"no daemon reachable: {exc}", as_json)
            return EXIT_UNREACHABLE
        except RequestError as exc:
            error = exc.reply.get("error", {})
            details = {k: v for k, v in error.items() if k not in ("code", "reason")}
            print_error(
                exc.code, exc.reason, as_json, details, prefix=f"{name}: refused ({exc.code})"
            )
            return EXIT_FAILED
        except MotionInterruptedError as exc:
            print_error(exc.code, exc.reason, as_json, exc.details, prefix=f"{name}: {exc.code}")
            return EXIT_FAILED
        except ClientError as exc:  # several daemons and no --prefix, a foreign reply
            print_error("usage", str(exc), as_json, prefix="usage error")
            return EXIT_USAGE
        print_result(result, as_json)
        return EXIT_OK

    return run


def _watch_state(client: CdprClient, line: ProgressLine) -> list[zenoh.Subscriber]:
    """The progress of a procedure the daemon runs (home, pretension): the safety state,
    and a pretension's phase, from the published state; the time elapsed (the daemon
    does not say how long it takes)."""

    def on_state(state: dict[str, Any]) -> None:
        phase = str(state.get("state", ""))
        pretension = state.get("pretension")
        if phase == "pretension" and isinstance(pretension, dict):
            phase = f"pretension: {pretension.get('phase')}"
        line.update(phase=phase)

    return [client.subscribe_state(on_state)]


def _watch_identify(client: CdprClient, line: ProgressLine) -> list[zenoh.Subscriber]:
    """identify-payload's progress: the poses it flies to (one goto each, then back to
    where it began: daemon.service.identify_payload), counted from the daemon's events
    ("goto accepted"); the ETA extrapolated from the poses done."""
    from cdpr.pose import Pose
    from daemon.service.identify_payload import identification_poses

    poses = len(identification_poses(Pose((0.0, 0.0, 0.0))))
    gotos = [0]

    def shown() -> None:
        k = gotos[0]
        phase = "starting" if k == 0 else f"pose {k} of {poses}" if k <= poses else "returning"
        line.update(max(k - 1, 0) / (poses + 1), phase)

    def on_event(event: dict[str, Any]) -> None:
        if event.get("event") == "state" and event.get("why") == "goto accepted":
            gotos[0] += 1
            shown()

    return [client.subscribe_events(on_event), client.subscribe_state(lambda _: shown())]


def _wait_for_end(
    client: CdprClient,
    accepted: Mapping[str, Any],
    ident: str | None,
    states: queue.Queue[dict[str, Any]],
    line: ProgressLine,
) -> dict[str, Any]:
    """Follow the motion `accepted` (the daemon's reply: start, end and duration on its
    clock, the state's "t") through the published `states` until it ends: the last
    state's safety state, fault and time if it holds its last pose; MotionInterruptedError if it
    braked or was stopped (replaced, held, disabled) before its end.  Ours while the
    state's "motion" names this client (and `ident`, a trajectory's id)."""
    try:
        start, end = float(accepted["start"]), float(accepted["end"])
    except (KeyError, TypeError, ValueError):
        raise ClientError(
            f"the daemon's reply says no start and end to wait for: {accepted}"
        ) from None
    length = max(end - start, 0.0)
    seen_ours = False
    while True:
        try:
            state = states.get(timeout=client.timeout)
        except queue.Empty:
            raise UnreachableError(
                f"no state from the daemon for {client.timeout:g} s while waiting"
            ) from None
        t = state.get("t")
        if not isinstance(t, int | float):
            raise ClientError("the daemon's state carries no time (t) to follow the motion by")
        safety, motion = state.get("state"), state.get("motion", {})
        ours = motion == {} or (
            isinstance(motion, dict)
            and motion.get("client") == client.name
            and motion.get("id") == ident
        )
        seen_ours = seen_ours or (ours and motion != {})
        outcome = {"state": safety, "fault": state.get("fault"), "motion": motion or None, "t": t}
        fraction = 1.0 if length == 0.0 else (t - start) / length
        line.update(fraction, "waiting for its start" if t < start else "flying", max(end - t, 0.0))
        if safety == "braked":
            fault = state.get("fault") or {}
            why = f"{fault.get('trigger')}: {fault.get('message')}" if fault else "no fault given"
            raise MotionInterruptedError(
                "braked", f"the robot braked ({why})", {"accepted": dict(accepted), **outcome}
            )
        if t >= end and (safety == "hold" or (seen_ours and not ours)):
            return outcome
        if (t >= end and safety != "tracking") or (
            seen_ours and not ours and t < end - STOPPED_GRACE
        ):
            raise MotionInterruptedError(
                "stopped",
                f"the motion was stopped {max(end - t, 0.0):.1f} s before its end: the robot is "
                f"{safety}, running {motion or 'nothing'}",
                {"accepted": dict(accepted), **outcome},
            )


def _flown(
    send: Callable[[CdprClient], dict[str, Any]], wait: bool, reply_of: Callable[[dict], dict]
) -> Action:
    """`send` the motion; with `wait`, follow it to its end (_wait_for_end) and add the
    "outcome" to the reply.  `reply_of`: the accepted part of the reply (start, end)."""

    def act(client: CdprClient, line: ProgressLine) -> dict[str, Any]:
        if not wait:
            return send(client)
        states: queue.Queue[dict[str, Any]] = queue.Queue()
        subscriber = client.subscribe_state(states.put)
        try:
            reply = send(client)
            while not states.empty():  # taken before the daemon accepted it
                states.get_nowait()
            ident = reply.get("id") if "result" in reply and "id" in reply else None
            outcome = _wait_for_end(client, reply_of(reply), ident, states, line)
        finally:
            subscriber.undeclare()
        return {**reply, "outcome": outcome}

    return act


def _prepare_send(args: argparse.Namespace) -> Action:
    """A trajectory file as it is; a path (--path) or G-code (--gcode) read here, so that
    a bad pose or line is a usage error before any network, and sent as a path."""
    start = _start(args.start)
    accepted: Callable[[dict], dict] = lambda reply: reply.get("result", {})  # noqa: E731
    if not (args.path or args.gcode):
        body = read_mapping(args.file)
        return _flown(
            lambda client: client.send_trajectory(
                body, start=start, request_id=args.id, preempt=args.preempt
            ),
            args.wait,
            accepted,
        )
    from daemon.config import load_config

    if args.gcode and args.config is None:
        raise UsageError("--gcode needs --config: the G-code starts at the robot's home")
    try:
        config = None if args.config is None else load_config(args.config)
        path = read_path(args.file, config, args.blend, gcode=args.gcode)
    except ConfigError as exc:
        raise UsageError(str(exc).strip()) from None
    except TrajectoryError as exc:
        raise UsageError(f"{args.file}: {exc}") from None
    return _flown(
        lambda client: client.send_path(
            path, start=start, request_id=args.id, preempt=args.preempt
        ),
        args.wait,
        accepted,
    )


def _prepare_request(name: str) -> Callable[[argparse.Namespace], Action]:
    return lambda _args: lambda client, _: client.request(name)


def _prepare_goto(args: argparse.Namespace) -> Action:
    position, quaternion = _pose(args.pose)
    return _flown(
        lambda client: client.goto(position, quaternion, args.preempt), args.wait, lambda r: r
    )


def _start(text: str) -> float | None:
    if text == "now":
        return None
    try:
        start = float(text)
    except ValueError:
        raise UsageError(
            f'--start: expected "now" or a unix time in seconds, got {text!r}'
        ) from None
    if not (math.isfinite(start) and start > 0.0):
        raise UsageError(f"--start: {text!r} is not a unix time in seconds")
    return start


def _pose(values: list[str]) -> tuple[list[float], dict[str, float] | None]:
    if len(values) not in (3, 7):
        raise UsageError(f"goto takes x y z [qw qx qy qz]: 3 or 7 numbers, got {len(values)}")
    try:
        numbers = [float(v) for v in values]
    except ValueError as exc:
        raise UsageError(f"goto: {exc}") from None
    if not all(math.isfinite(v) for v in numbers):
        raise UsageError("goto: every number must be finite")
    quaternion = None if len(numbers) == 3 else dict(zip("wxyz", numbers[3:], strict=True))
    return numbers[:3], quaternion
