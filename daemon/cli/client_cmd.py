"""The `cdprd` client commands: send a trajectory, run a command, print the daemon's reply.

    cdprd send FILE [--start now|UNIX_TIME] [--id ID] [--preempt]  (YAML or JSON)
    cdprd send FILE --path | --gcode --config CFG [--blend M]  (a path the daemon times)
    cdprd status | enable | disable | hold | reset
    cdprd brake [--reason TEXT]
    cdprd goto x y z [qw qx qy qz] [--preempt]
    cdprd identify-payload [--apply] [--preempt]
    cdprd payload [--freeze [--lease S] | --unfreeze] [--lease-id ID]
    cdprd observer [--hold [--lease S] | --release] [--lease-id ID]  (the wrench observer)
    cdprd home [--pose NAME] [--preempt]  (the platform resting at the robot file's pose)
    cdprd pretension [--pose NAME] [--preempt]  (from slack cables, on a fixture there)
    common options: --prefix cdpr/<robot>  --connect tcp/127.0.0.1:7448  --timeout S
                    --zenoh-config FILE (raw zenoh keys, e.g. TLS certificates)
                    --client NAME (who asks, in the daemon's events; default user@host:pid)

--preempt replaces a motion another client runs (refused otherwise, naming it); a lease
taken with --lease prints its lease_id, which --lease-id gives to renew or release it.

Exit codes: 0 accepted / done, 1 the daemon refused (the reason is printed), 2 usage
(bad arguments, unreadable file, several daemons and no --prefix), 3 no daemon reachable.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from typing import Any

from cdpr.description import ConfigError
from cdpr.trajectory import TrajectoryError
from daemon.cli.exit_codes import EXIT_FAILED, EXIT_OK, EXIT_UNREACHABLE, EXIT_USAGE
from daemon.cli.input_files import UsageError, read_mapping, read_path
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
IDENTIFY_TIMEOUT = 120.0  # s: identify-payload moves through five poses
PRETENSION_TIMEOUT = 120.0  # s: winding in (up to pretension.taut_timeout), ramp, settle
_SIMPLE = {
    "status": "print the daemon's safety state",
    "enable": "enable the drives (IDLE -> ENABLED, holding the current pose)",
    "disable": "stop moving and disable the drives (brakes on)",
    "hold": "stop smoothly and hold the pose",
    "reset": "leave BRAKED once the fault is gone",
}


Action = Callable[[CdprClient], Any]


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
    send = subparsers.add_parser(
        "send", parents=[common], help="send a trajectory file (YAML or JSON) and await the verdict"
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
    send.set_defaults(run=_runner("send", _prepare_send))
    for name, text in _SIMPLE.items():
        sub = subparsers.add_parser(name, parents=[common], help=text)
        sub.set_defaults(run=_runner(name, _prepare_request(name)))
    brake = subparsers.add_parser(
        "brake", parents=[common], help="brake now (cable lengths frozen)"
    )
    brake.add_argument("--reason", help="why, recorded with the fault")
    brake.set_defaults(run=_runner("brake", lambda args: lambda c: c.brake(args.reason)))
    goto = subparsers.add_parser("goto", parents=[common], help="move smoothly to a pose")
    goto.add_argument(
        "pose", nargs="+", metavar="x y z [qw qx qy qz]", help="position (m), quaternion"
    )
    goto.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
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
    identify.set_defaults(
        run=_runner("identify_payload", lambda a: lambda c: c.identify_payload(a.apply, a.preempt)),
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
            lambda a: lambda c: c.payload(a.frozen, lease=a.lease, lease_id=a.lease_id),
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
        run=_runner("observer", lambda a: lambda c: c.observer(a.held, a.lease, a.lease_id))
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
    home.set_defaults(run=_runner("home", lambda a: lambda c: c.home(a.pose, a.preempt)))
    pretension = subparsers.add_parser(
        "pretension",
        parents=[common],
        help="wind slack cables in, tension them without moving the platform, close the loop",
    )
    pretension.add_argument(
        "--pose", help="the robot file's pose (poses:) of the fixture it rests on (default home)"
    )
    pretension.add_argument("--preempt", action="store_true", help=PREEMPT_HELP)
    pretension.set_defaults(
        run=_runner("pretension", lambda a: lambda c: c.pretension(a.pose, a.preempt)),
        timeout=PRETENSION_TIMEOUT,
    )


def _runner(
    name: str, prepare: Callable[[argparse.Namespace], Action]
) -> Callable[[argparse.Namespace], int]:
    """args -> exit code: check the arguments (`prepare`, before any network), connect,
    run the action, print the result or the reason."""

    def run(args: argparse.Namespace) -> int:
        try:
            if not (args.timeout > 0 and math.isfinite(args.timeout)):
                raise UsageError(f"--timeout must be a positive number of seconds: {args.timeout}")
            action = prepare(args)
            raw = None if args.zenoh_config is None else read_mapping(args.zenoh_config)
            with CdprClient(
                args.prefix,
                args.connect or default_connect(),
                timeout=args.timeout,
                zenoh_config=raw,
                name=args.client,
            ) as client:
                result = action(client)
        except UsageError as exc:
            print(f"usage error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        except UnreachableError as exc:
            print(f"error: no daemon reachable: {exc}", file=sys.stderr)
            return EXIT_UNREACHABLE
        except RequestError as exc:
            print(f"{name}: refused ({exc.code}): {exc.reason}", file=sys.stderr)
            error = exc.reply.get("error", {})
            details = {k: v for k, v in error.items() if k not in ("code", "reason")}
            if details:
                print(f"  {json.dumps(details)}", file=sys.stderr)
            return EXIT_FAILED
        except ClientError as exc:  # several daemons and no --prefix, a foreign reply
            print(f"usage error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        print(json.dumps(result, indent=2 if name == "status" else None))
        return EXIT_OK

    return run


def _prepare_send(args: argparse.Namespace) -> Action:
    """A trajectory file as it is; a path (--path) or G-code (--gcode) read here, so that
    a bad pose or line is a usage error before any network, and sent as a path."""
    start = _start(args.start)
    if not (args.path or args.gcode):
        body = read_mapping(args.file)
        return lambda client: client.send_trajectory(
            body, start=start, request_id=args.id, preempt=args.preempt
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
    return lambda client: client.send_path(
        path, start=start, request_id=args.id, preempt=args.preempt
    )


def _prepare_request(name: str) -> Callable[[argparse.Namespace], Action]:
    return lambda _args: lambda client: client.request(name)


def _prepare_goto(args: argparse.Namespace) -> Action:
    position, quaternion = _pose(args.pose)
    return lambda client: client.goto(position, quaternion, args.preempt)


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
