"""`cdprd calibrate`: identify the robot's geometry from redundant cable lengths
(DESIGN §15 step 5).

    cdprd calibrate --config FILE SCALE [--poses N] [--reach X Y Z] [--tilt RAD] [--dwell S]
                    [--average S] [--resume]
                    [--output FILE] [--json]   + the client options (--prefix, --connect)
    cdprd calibrate --config FILE SCALE --from-recording RUN.mcap [--output FILE] [--json]
    SCALE: --scale-distance A,B,METRES | --no-scale

Flying: the daemon must be enabled (HOLD).  Poses are picked for identifiability
(greedy D-optimal from random candidates within --reach of home and --tilt of its
orientation, inside the limits a goto keeps and the cables' limits), flown to one by one
by slow rest-to-rest trajectories (SPEED), and at each the lengths and commanded forces
are averaged over the last --average s of --dwell (default its second half), from the
published state, while the platform flies a small loop (DITHER) about the pose: at rest
each length reads the same encoder count all along, whose rounding (15 um on reference8's
drives) is then an error of every sample that the fit amplifies (the identification is
ill-conditioned: condition numbers of thousands); swept over a few counts the average
resolves the length far finer, and the loop's effect on the mean length (its curvature,
DITHER^2 / length) is nanometres.  From a
recording: the telemetry MCAP of a run (recording.telemetry, or run --record), every
stretch of at least 0.6 s at rest giving a pose.  Either way tuning.calibration solves
for the anchors, attachments, each cable's length offset and drum radius, and the
cables' EA, and reports which are identifiable (singular values and condition number of
the identification Jacobian, the poses eliminated; the gauge freedoms fixed as
tuning.calibration says), the fit residual, and progress on stderr while it flies and
solves.

The round is kept on disk (daemon.cli.calibration_round: the poses planned and each one
recorded, checked to belong to this robot and the offsets in force): a brake while
flying ends the command naming the brake's trigger and message, with what the poses
recorded so far identify (rank and condition of the identification Jacobian, what is not
identifiable yet), and `--resume` (after `cdprd reset` and `cdprd enable`) flies the
poses not yet flown and solves with all of them.

Scale: lengths alone cannot see a common drum radius error (a robot and its drums scaled
together read the same lengths), so the command asks for one measured distance,
`--scale-distance A,B,METRES` between the anchor points of cables A and B (0-based, as
the robot file lists them), which scales the fit (tuning.calibration.scaled), or
`--no-scale`, the drums' mean radius taken as the file's; either way it says what a 1 %
drum error costs this robot (tuning.calibration.scale_cost).

Writes the corrected robot file beside the old one (ROBOT.calibrated-YYYYmmdd-HHMMSS.yaml,
or --output; an existing file is never overwritten) and, where the config has a
state_dir, the calibrated offsets as the stored state (method "calibrate"): restart the
daemon with the new robot file (robot: in the config) to fly it.  The offsets the
lengths were read with are the daemon's in force (status) when flying; a recording's
cycle records carry the lengths as the drivers read them, with drives.length_offset.

Exit codes: 0 done, 1 refused or failed (the reason is printed; too few poses names the
parameters that cannot be identified), 2 usage, 3 no daemon reachable.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from cdpr import ConfigError, Pose, Robot, liediff
from daemon.cli.exit_codes import EXIT_FAILED, EXIT_OK, EXIT_UNREACHABLE, EXIT_USAGE
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.progress import ProgressLine, add_progress_flag, progress_line
from daemon.cli.run_cmd import load_checked
from daemon.cli.run_cmd import report as report_config
from tuning.calibration import AnchorDistance

if TYPE_CHECKING:
    from cdpr.trajectory import Trajectory
    from daemon.cli.calibration_round import CalibrationRound
    from daemon.config import DaemonConfig
    from daemon.interface.client import CdprClient, RequestError
    from tuning.calibration import Calibration, Sample

SPEED = 0.2  # m/s (and rad/s) of the moves between poses
MOVE_MIN = 1.5  # s: the shortest move
MIN_POSES = 8  # below this the command refuses before flying
DITHER = 2e-4  # m: the loop flown about each pose while its state is averaged
DITHER_STEPS = 7  # moves of the loop: to each of the six corners and back
LEASE = 5.0  # s: the lease on the payload freeze and the observer hold (daemon.service.lease)
RENEW_PERIOD = 1.0  # s between its renewals while flying
SCALE_MISMATCH = 0.05  # a measured distance this far (relative) from the file's: a mistake
COST_ERROR = 0.01  # the common drum radius error whose cost is reported
COST_REACH = 0.3  # m from home: the goto whose error is reported


class CalibrationError(Exception):
    """The calibration cannot go on (the message says why)."""


def add_parser(subparsers: Any) -> None:
    from daemon.interface.client import CONNECT_ENV, DEFAULT_CONNECT

    p = subparsers.add_parser(
        "calibrate",
        help="identify anchors, attachments, offsets, drum radii and EA from redundant lengths",
    )
    p.add_argument("--config", required=True, help="the daemon's config YAML")
    p.add_argument("--from-recording", metavar="MCAP", help="a run's telemetry instead of flying")
    p.add_argument("--poses", type=int, default=40, help="poses to fly (default 40)")
    p.add_argument(
        "--reach", type=float, nargs=3, default=(0.6, 0.6, 0.45), metavar=("X", "Y", "Z"),
        help="how far from home the poses may lie, m per axis (default 0.6 0.6 0.45)",
    )  # fmt: skip
    p.add_argument("--tilt", type=float, default=0.2, help="largest tilt from home, rad")
    p.add_argument("--dwell", type=float, default=1.5, help="seconds at rest at each pose")
    p.add_argument(
        "--average", type=float, help="seconds at the end of each dwell averaged (default: half)"
    )
    p.add_argument("--seed", type=int, default=0, help="of the candidate poses")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument(
        "--scale-distance", type=_anchor_distance, metavar="A,B,METRES",
        help="the measured distance between the anchors of cables A and B (0-based): the scale",
    )  # fmt: skip
    scale.add_argument(
        "--no-scale", action="store_true",
        help="calibrate without a scale reference (what that costs is printed)",
    )  # fmt: skip
    p.add_argument(
        "--resume", action="store_true",
        help="continue the round a brake interrupted (its poses kept on disk)",
    )  # fmt: skip
    p.add_argument("--output", help="the corrected robot file (default: beside the old one)")
    add_json_flag(p)
    add_progress_flag(p)
    p.add_argument("--prefix", help="key prefix of the daemon (default: the only one)")
    p.add_argument(
        "--connect",
        help=f"zenoh endpoint of the daemon (default ${CONNECT_ENV}, else {DEFAULT_CONNECT})",
    )
    p.add_argument("--timeout", type=float, default=10.0, help="seconds per daemon request")
    p.set_defaults(handler=run)


def _anchor_distance(text: str) -> AnchorDistance:
    """--scale-distance A,B,METRES: two different cables and a distance in metres."""
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError(text)
        first, second, metres = int(parts[0]), int(parts[1]), float(parts[2])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected A,B,METRES (two cable indices and metres), e.g. 0,5,4.9244"
        ) from None
    if min(first, second) < 0 or first == second:
        raise argparse.ArgumentTypeError(f"{text!r}: expected two different cables (0-based)")
    if not (math.isfinite(metres) and metres > 0.0):
        raise argparse.ArgumentTypeError(f"{text!r}: the distance must be more than 0 m")
    return AnchorDistance(first, second, metres)


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _usage(reason: str, as_json: bool) -> None:
    print_error("usage", reason, as_json, prefix="usage error")


def _scale_cost(robot: Robot) -> str:
    """What an unknown scale costs `robot`, in words."""
    from tuning.calibration import scale_cost

    anchors, goto = scale_cost(robot, COST_ERROR, COST_REACH)
    return (
        f"on {robot.name} a {COST_ERROR:.0%} drum radius error leaves the anchors up to "
        f"{anchors * 1e3:.1f} mm off and a goto {COST_REACH:g} m from home up to "
        f"{goto * 1e3:.1f} mm off"
    )


def _scale_problem(robot: Robot, args: argparse.Namespace) -> str | None:
    """Why the scale reference given cannot be used (None: it can, or it is waived)."""
    distance = args.scale_distance
    if distance is None:
        if args.no_scale:
            return None
        return (
            "a scale reference is needed: give --scale-distance A,B,METRES (the measured "
            "distance between the anchor points of cables A and B, 0-based as the robot "
            "file lists them; the farther apart the better), or --no-scale to calibrate "
            "without one.  Cable lengths alone cannot see a common drum radius error: "
            + _scale_cost(robot)
        )
    n = robot.n_cables
    for cable in (distance.first, distance.second):
        if cable >= n:
            return f"--scale-distance: cable {cable}: {robot.name} has cables 0 to {n - 1}"
    anchors = np.asarray(robot.geometry.anchors, dtype=float)
    in_file = float(np.linalg.norm(anchors[distance.first] - anchors[distance.second]))
    if abs(distance.metres - in_file) > SCALE_MISMATCH * in_file:
        return (
            f"--scale-distance: the anchors of cables {distance.first} and {distance.second} "
            f"are {in_file:.4f} m apart in the robot file, {distance.metres:.4f} m measured: "
            f"more than {SCALE_MISMATCH:.0%} apart (check the cables and that it is in metres)"
        )
    return None


def run(args: argparse.Namespace) -> int:
    try:
        config = load_checked(args.config)
    except ConfigError as exc:
        report_config(exc, args.json)
        return EXIT_USAGE
    if args.poses < MIN_POSES and args.from_recording is None:
        _usage(f"--poses: at least {MIN_POSES}", args.json)
        return EXIT_USAGE
    average = args.dwell / 2 if args.average is None else args.average
    if not 0.0 < average <= args.dwell:
        _usage(f"--average: more than 0 s, at most --dwell ({args.dwell:g} s)", args.json)
        return EXIT_USAGE
    args.average = average
    problem = _scale_problem(config.robot, args)
    if problem is not None:
        _usage(problem, args.json)
        return EXIT_USAGE
    if args.resume and args.from_recording is not None:
        _usage("--resume continues a flown round, not --from-recording", args.json)
        return EXIT_USAGE
    output = _output_path(config, args.output)
    if output.exists():
        print_error("usage", f"{output} exists: not overwritten (give another --output)", args.json)
        return EXIT_USAGE
    from daemon.interface.client import RequestError, UnreachableError

    started = time.perf_counter()
    try:
        if args.from_recording is not None:
            offsets, samples = _from_recording(config, Path(args.from_recording))
            calibration = _solve(config.robot, offsets, samples, args.progress)
            planned = len(samples)
        else:
            calibration, planned = _fly_and_solve(config, args)
        calibration, scale = _scaled(config.robot, calibration, args.scale_distance)
    except UnreachableError as exc:
        print_error("unreachable", f"no daemon reachable: {exc}", args.json)
        return EXIT_UNREACHABLE
    except RequestError as exc:
        print_error(exc.code, _refused(exc), args.json)
        return EXIT_FAILED
    except CalibrationError as exc:
        print_error("failed", str(exc), args.json)
        return EXIT_FAILED
    seconds = time.perf_counter() - started
    from tuning.calibration import corrected_robot

    corrected = corrected_robot(config.robot, calibration)
    _write_new(output, corrected, calibration)
    stored = _store_offsets(config, calibration, output)
    report = {
        **calibration.report(),
        "planned": planned,
        "scale": scale,
        "robot_file": str(output),
        "offsets_stored": stored,
        "seconds": seconds,
    }
    print_result(report, args.json, lambda: _print_report(report, calibration))
    return EXIT_OK


def _output_path(config: DaemonConfig, given: str | None) -> Path:
    if given is not None:
        return Path(given)
    raw = config.raw.robot
    source = config.path(raw) if isinstance(raw, str) else config.base / f"{config.robot.name}.yaml"
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return source.with_name(f"{source.stem}.calibrated-{stamp}.yaml")


def _solve(
    robot: Robot, offsets: np.ndarray, samples: list[Sample], progress: bool = False
) -> Calibration:
    """The fit of `samples`, its progress on the live line (`progress`: --progress)."""
    from tuning.calibration import identify

    _say(f"solving: {len(samples)} poses")
    try:
        with progress_line("calibrate", progress) as line:
            calibration = identify(
                robot, offsets, samples, progress=lambda text: line.update(phase=text)
            )
    except ValueError as exc:
        raise CalibrationError(f"calibration failed: {exc}") from None
    if not calibration.converged:
        raise CalibrationError(
            f"the fit did not converge in {calibration.iterations} evaluations (residual RMS "
            f"{calibration.residual_rms * 1e3:.4f} mm): check the data, fly more poses"
        )
    if calibration.unidentifiable:
        raise CalibrationError(
            f"{len(samples)} poses do not identify every parameter ("
            f"{len(calibration.unidentifiable)} combinations unidentifiable; fly more poses, "
            "further apart): " + "; ".join(calibration.unidentifiable)
        )
    return calibration


def _scaled(
    robot: Robot, calibration: Calibration, distance: AnchorDistance | None
) -> tuple[Calibration, dict[str, Any]]:
    """The fit scaled to the measured `distance` (as it is without one), and the scale as
    the report gives it: the distance measured and fitted, and their ratio, the factor
    the fit was scaled by; or none, and what that costs."""
    from tuning.calibration import scale_cost, scaled

    if distance is None:
        anchors, goto = scale_cost(robot, COST_ERROR, COST_REACH)
        cost = {"cost_anchors_mm": anchors * 1e3, "cost_goto_mm": goto * 1e3}
        return calibration, {"reference": None, "cost": _scale_cost(robot), **cost}
    a = calibration.anchors
    fitted = float(np.linalg.norm(a[distance.first] - a[distance.second]))
    try:
        found = scaled(calibration, distance)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    return found, {
        "reference": f"anchors of cables {distance.first} and {distance.second}",
        "measured_m": distance.metres,
        "fitted_m": fitted,
        "factor": distance.metres / fitted,
    }


def _fly_and_solve(config: DaemonConfig, args: argparse.Namespace) -> tuple[Calibration, int]:
    """Fly the round (a new one, or the kept one with --resume) and solve: (the fit, the
    poses planned).  Once every planned pose has been flown the round is over and its
    file removed, whatever the solve finds (too few poses: fly a new round)."""
    from daemon.cli.calibration_round import round_path

    path = round_path(config)
    calibration_round = _fly(config, args, path)
    samples = calibration_round.samples()
    try:
        offsets = np.array(calibration_round.offsets)
        calibration = _solve(config.robot, offsets, samples, args.progress)
    finally:
        path.unlink(missing_ok=True)
    return calibration, len(calibration_round.planned)


def _plan(config: DaemonConfig, args: argparse.Namespace) -> list[Pose]:
    """The poses of a new round (module docstring)."""
    from tuning.calibration import candidate_poses, select_poses

    robot = config.robot
    rng = np.random.default_rng(args.seed)
    limits = config.reference_limits  # what a goto's samples must keep
    candidates = [
        p
        for p in candidate_poses(robot, 10 * args.poses, rng, args.reach, args.tilt)
        if limits.violation(p) is None
    ]
    if len(candidates) < args.poses:
        raise CalibrationError(
            f"only {len(candidates)} candidate poses lie in the workspace: reduce --poses "
            "or widen --reach"
        )
    poses = select_poses(robot, args.poses, candidates)
    _say(f"flying {len(poses)} poses (greedy D-optimal of {len(candidates)} candidates)")
    return poses


def _kept_round(robot: Robot, identity: str, path: Path, resume: bool) -> CalibrationRound | None:
    """The round kept in `path` to resume (None: --resume not given); refused when there
    is none to resume, or one that a new round would throw away."""
    from daemon.cli.calibration_round import RoundFileError, load_round

    try:
        kept = load_round(path, robot.name, robot.n_cables, identity)
    except RoundFileError as exc:
        raise CalibrationError(f"{exc}: remove it to fly a new round") from None
    if kept is None:
        if resume:
            raise CalibrationError(f"no round to resume: {path} does not exist")
        return None
    recorded = f"{len(kept.recorded)} of {len(kept.planned)} poses recorded"
    if not resume:
        raise CalibrationError(
            f"{path} holds a round interrupted with {recorded}: continue it with --resume, "
            "or remove the file to fly a new round"
        )
    _say(f"resuming the round in {path}: {recorded}, {len(kept.remaining())} to fly")
    return kept


def _fly(config: DaemonConfig, args: argparse.Namespace, path: Path) -> CalibrationRound:
    """Fly the poses of the round not yet flown, keeping each in `path` (module
    docstring); the round, every pose flown.  Interrupted (a brake, SIGTERM, a lost
    lease, a refusal), a CalibrationError says why, and what the poses kept identify."""
    from daemon.cli.calibration_round import CalibrationRound
    from daemon.interface.client import CdprClient, RequestError, default_connect
    from daemon.service.calibration_state import robot_identity

    robot = config.robot
    identity = robot_identity(robot, config.drives)
    kept = _kept_round(robot, identity, path, args.resume)
    if kept is not None and not kept.remaining():
        return kept  # flown to the end, but not solved: interrupted in between
    poses = _plan(config, args) if kept is None else []
    with CdprClient(args.prefix, args.connect or default_connect(), timeout=args.timeout) as client:
        status = client.status()
        if status["state"] != "hold":
            fault = status.get("fault")
            why = "" if not fault else f" on {fault['trigger']}: {fault['message']}"
            raise CalibrationError(
                f"the daemon is {status['state']}{why}: reset it if braked (cdprd reset) and "
                "enable it (cdprd enable) at rest first"
            )
        offsets = [float(x) for x in status["offsets"]["values"]]
        if kept is None:
            calibration_round = CalibrationRound(robot.name, identity, offsets, poses)
            _keep(path, calibration_round)
        elif offsets != kept.offsets:
            raise CalibrationError(
                "the daemon's offsets are not those the kept round's lengths were read with "
                f"(homed since?): its poses cannot be combined with new ones; remove {path} "
                "to fly a new round"
            )
        else:
            calibration_round = kept
        try:
            with _file_model(client, robot), progress_line("calibrate", args.progress) as line:
                dither = dither_amplitude(args.average, config.trajectory.linear_jerk)
                _record_poses(
                    client, calibration_round, path, args.dwell, args.average, dither, line
                )
        except (RequestError, CalibrationError) as exc:
            why = _refused(exc) if isinstance(exc, RequestError) else str(exc)
            raise CalibrationError(f"{why}\n{_kept_note(robot, calibration_round, path)}") from None
    return calibration_round


def _refused(exc: RequestError) -> str:
    return f"the daemon refused ({exc.code}): {exc.reason}"


def _keep(path: Path, calibration_round: CalibrationRound) -> None:
    """Write the round to `path`; CalibrationError if it cannot."""
    from daemon.cli.calibration_round import save_round

    try:
        save_round(path, calibration_round)
    except OSError as exc:
        raise CalibrationError(f"cannot keep the round in {path}: {exc}") from None


def _kept_note(robot: Robot, calibration_round: CalibrationRound, path: Path) -> str:
    """What an interrupted round keeps, how to continue it, and what its poses identify
    so far (tuning.calibration.survey: said, not fitted)."""
    from tuning.calibration import survey

    samples = calibration_round.samples()
    planned = len(calibration_round.planned)
    lines = [
        f"{len(samples)} of {planned} poses recorded, kept in {path}: reset and enable the "
        "daemon (cdprd reset, cdprd enable), then continue the round with cdprd calibrate "
        "--resume (the same --config and scale options)"
    ]
    if len(samples) < 2:
        lines.append("too few poses recorded to identify anything yet")
        return "\n".join(lines)
    try:
        found = survey(robot, np.array(calibration_round.offsets), samples)
    except ValueError as exc:
        lines.append(f"what the poses recorded identify cannot be said: {exc}")
        return "\n".join(lines)
    lines.append(
        f"so far the {found.poses} poses recorded identify {found.rank} of {found.parameters} "
        f"parameter combinations (identification Jacobian, poses eliminated, columns scaled: "
        f"condition {found.condition:.3g}); not yet identifiable: "
        f"{len(found.unidentifiable)}"
        + (f", e.g. {found.unidentifiable[0]}" if found.unidentifiable else "")
    )
    return "\n".join(lines)


@contextlib.contextmanager
def _file_model(client: CdprClient, robot: Robot) -> Iterator[None]:
    """While flying, the robot file's model alone in the daemon's loop: its platform, the
    payload estimate frozen, and the external wrench observer held out of the loop
    (ParallelController.hold_observer); both let go after, however the flight ends.  An
    uncalibrated geometry looks like a payload to the estimate (cdpr.payload), which would
    drift to its limit (adaptation.com_max) and brake, and like an external wrench to the
    observer, which would compensate it while the poses are flown (anchors twice as far
    off); the forces recorded are whatever holds the platform either way.  SIGTERM
    meanwhile is an error (`_terminated`), so that they are let go then too; both are
    held on a LEASE renewed meanwhile (`_renewing`), so that the daemon lets go of them
    itself when this process dies unable to (kill -9, its machine or network gone)."""
    platform = robot.platform
    com = [float(c) for c in platform.center_of_mass]
    with contextlib.ExitStack() as held:
        previous = signal.signal(signal.SIGTERM, _terminated)
        held.callback(signal.signal, signal.SIGTERM, previous)
        renewals = []
        if held.enter_context(
            _held(
                lambda: client.payload(True, platform.mass, com, lease=LEASE),
                lambda: client.payload(False),
            )
        ):
            renewals.append(lambda: client.payload(True, lease=LEASE))
        if held.enter_context(
            _held(lambda: client.observer(True, lease=LEASE), lambda: client.observer(False))
        ):
            renewals.append(lambda: client.observer(True, lease=LEASE))
        held.enter_context(_renewing(renewals))
        yield


@contextlib.contextmanager
def _held(hold: Callable[[], object], release: Callable[[], object]) -> Iterator[bool]:
    """`hold()` a part of the daemon's model, `release()` it on the way out, however;
    whether it holds: nothing to do when the daemon has it off (the request refused with
    invalid_state)."""
    from daemon.interface.client import RequestError

    try:
        hold()
    except RequestError as exc:
        if exc.code != "invalid_state":
            raise
        yield False
        return
    try:
        yield True
    finally:
        try:
            release()
        except RequestError as exc:
            if exc.code != "not_owner":
                raise
            _say(f"nothing to let go: {exc.reason}")  # the lease lapsed: it was let go


@contextlib.contextmanager
def _renewing(renewals: list[Callable[[], object]]) -> Iterator[None]:
    """Call every renewal each RENEW_PERIOD s on a thread of its own while the flight
    sleeps and waits on the daemon; stopped before the flight lets go.  A renewal that
    fails, or none getting through within the LEASE, fails the calibration when the
    flight ends (the daemon may have let go meanwhile: the poses flown then are suspect)."""
    from daemon.interface.client import ClientError

    stop = threading.Event()
    failures: list[str] = []

    def renew() -> None:
        renewed = time.monotonic()
        while not stop.wait(RENEW_PERIOD):
            try:
                for renewal in renewals:
                    renewal()
            except ClientError as exc:
                failures.append(f"the daemon's lease was not renewed: {exc}")
                return
            now = time.monotonic()
            if now - renewed > LEASE:
                failures.append(
                    f"the daemon's lease was renewed {now - renewed:.1f} s after the last time, "
                    f"beyond its {LEASE:g} s: the daemon may have let go meanwhile"
                )
                return
            renewed = now

    thread = threading.Thread(target=renew, name="cdprd-calibrate-lease", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
    if failures:
        raise CalibrationError(failures[0] + ": fly again")


def _terminated(signum: int, frame: object) -> None:
    """SIGTERM while calibrating: an error, so that what the flight holds is let go."""
    raise CalibrationError("terminated (SIGTERM)")


def _record_poses(
    client: CdprClient,
    calibration_round: CalibrationRound,
    path: Path,
    dwell: float,
    average: float,
    dither: float,
    line: ProgressLine,
) -> None:
    """Move slowly to each pose of the round not yet flown (a rest-to-rest trajectory at
    SPEED, not a goto at the trajectory limits: the model is not calibrated yet), wait,
    average the state over the dither loop there (the module docstring), and keep it in
    the round and in `path`; a pose the daemon refuses to go to (the way leaves the
    wrench set, say) is skipped.  The daemon braking ends the flight at once, a
    CalibrationError naming the brake's trigger and message.  `dither`: the loop's
    amplitude (dither_amplitude); `line` shows the poses recorded of the round's."""
    from cdpr.trajectory import Trajectory, Waypoint
    from daemon.interface.client import RequestError
    from tuning.calibration import Sample

    rows: list[tuple[float, list[float], list[float]]] = []
    latest: list[Pose] = []
    faults: list[dict[str, Any] | None] = []
    braked = threading.Event()
    lock = threading.Lock()
    total = len(calibration_round.planned)
    flying = ["flying"]  # the phase shown, as the flight goes on
    before = len(calibration_round.recorded) + len(calibration_round.skipped)
    left = total - before  # the poses this command flies (--resume: the rest)

    def shown() -> None:
        done = len(calibration_round.recorded) + len(calibration_round.skipped) - before
        line.update(done / left, flying[0])

    def on_state(state: dict[str, Any]) -> None:
        if state.get("state") == "braked":
            with lock:
                faults.append(state.get("fault"))
            braked.set()
        elif state.get("state") in ("hold", "tracking") and "pose" in state:
            q = state["pose"]["quaternion"]
            with lock:
                latest[:] = [Pose(state["pose"]["position"], (q["w"], q["x"], q["y"], q["z"]))]
                rows.append((time.monotonic(), state["lengths"], state["forces"]))
        shown()

    def brake(k: int, fault: dict[str, Any] | None) -> CalibrationError:
        why = "(no fault given)" if not fault else f"on {fault['trigger']}: {fault['message']}"
        return CalibrationError(f"pose {k + 1} of {total}: the daemon braked {why}")

    def wait(seconds: float, k: int) -> None:
        """Sleep `seconds`, ended by a brake."""
        if braked.wait(seconds):
            with lock:
                raise brake(k, faults[0])

    def braked_now(k: int) -> CalibrationError | None:
        """The brake, if the daemon is braked now (the cause of a refusal)."""
        state = client.status()
        return brake(k, state.get("fault")) if state["state"] == "braked" else None

    subscriber = client.subscribe_state(on_state)
    k = calibration_round.remaining()[0]
    try:
        here = _wait_for_pose(latest, lock, braked)
        if here is None:  # it braked before it published a pose: the brake says why
            with lock:
                raise brake(k, faults[0])
        for k in calibration_round.remaining():
            target = calibration_round.planned[k]
            flying[0] = f"pose {k + 1} of {total}"
            error = liediff(here, target)
            distance = max(float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:])))
            move = max(MOVE_MIN, distance / SPEED)
            trajectory = Trajectory([Waypoint(0.0, here), Waypoint(move, target)])
            try:
                reply = client.send_trajectory(trajectory)
            except RequestError as exc:
                if exc.code != "rejected":
                    raise
                calibration_round.skipped[k] = exc.reason
                _keep(path, calibration_round)
                line.note(f"flying: pose {k + 1} of {total} refused, skipped: {exc.reason}")
                continue
            wait(float(reply["result"].get("duration", move)) + dwell - average, k)
            here = target
            with lock:
                rows.clear()
            _dither(client, target, average, dither)
            wait(average, k)
            with lock:
                recent = list(rows)
                rows.clear()
            if not recent:
                state = client.status()
                if state["state"] == "braked":
                    raise brake(k, state.get("fault"))
                raise CalibrationError(
                    f"pose {k + 1}: no state at rest from the daemon ({state['state']})"
                )
            calibration_round.recorded[k] = Sample(
                np.mean([r[1] for r in recent], axis=0), np.mean([r[2] for r in recent], axis=0)
            )
            _keep(path, calibration_round)
            line.note(f"flying: pose {k + 1} of {total} recorded")
    except RequestError as exc:
        raise braked_now(k) or exc from None
    finally:
        subscriber.undeclare()


def dither_amplitude(duration: float, linear_jerk: float | None) -> float:
    """The dither loop's amplitude (m): DITHER, or less where the trajectory limits'
    linear jerk allows less in `duration` (each of its DITHER_STEPS moves, up to sqrt(2)
    amplitudes from corner to corner, a rest-to-rest quintic whose jerk peaks at 60 d /
    T^3; the limit's share 0.99)."""
    if linear_jerk is None:
        return DITHER
    step = duration / DITHER_STEPS
    return min(DITHER, 0.99 * linear_jerk * step**3 / (60.0 * math.sqrt(2.0)))


def dither_loop(pose: Pose, duration: float, amplitude: float) -> Trajectory:
    """A loop of `amplitude` about `pose` (at rest there) lasting `duration`: through
    +-amplitude along each axis in turn and back, at rest at each corner (the daemon
    validates a transition's first segment as a trajectory of its own, which must end
    at rest)."""
    from cdpr.trajectory import Trajectory, Waypoint

    steps = [np.zeros(3)] + [amplitude * sign * axis for sign in (1, -1) for axis in np.eye(3)]
    dt = duration / DITHER_STEPS
    rest = np.zeros(6)
    waypoints = [
        Waypoint(k * dt, Pose(pose.position + step, pose.quaternion_tuple), rest, rest)
        for k, step in enumerate(steps)
    ]
    return Trajectory([*waypoints, Waypoint(duration, pose)])


def _dither(client: CdprClient, pose: Pose, duration: float, amplitude: float) -> None:
    """Send the dither_loop; if the daemon refuses it the platform stays at rest,
    averaged as it is."""
    from daemon.interface.client import RequestError

    try:
        client.send_trajectory(dither_loop(pose, duration, amplitude))
    except RequestError as exc:
        if exc.code != "rejected":
            raise


def _wait_for_pose(
    latest: list[Pose], lock: threading.Lock, braked: threading.Event, timeout: float = 5.0
) -> Pose | None:
    """The first measured pose the daemon publishes; None if it brakes first."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with lock:
            if latest:
                return latest[0]
        if braked.wait(0.05):
            return None
    raise CalibrationError(f"no state with a pose from the daemon within {timeout:g} s")


def _from_recording(config: DaemonConfig, path: Path) -> tuple[np.ndarray, list[Sample]]:
    """Samples at rest from a telemetry MCAP, and the offsets its lengths were read with."""
    from mcap.reader import make_reader

    from daemon.process.recording import CYCLE_TOPIC
    from tuning.calibration import rest_samples

    times, lengths, forces, twists = [], [], [], []
    try:
        with open(path, "rb") as stream:
            for _, _, message in make_reader(stream).iter_messages([CYCLE_TOPIC]):
                row = json.loads(message.data)
                if row.get("safety", {}).get("state") not in ("hold", "tracking"):
                    continue
                twist = row["twist"]
                times.append(row["t"])
                lengths.append([math.nan if x is None else x for x in row["lengths"]])
                forces.append([math.nan if x is None else x for x in row["forces"]])
                twists.append(twist["linear"] + twist["angular"])
    except (OSError, ValueError, KeyError) as exc:
        raise CalibrationError(f"{path}: cannot read the cycle records: {exc}") from None
    samples = rest_samples(times, lengths, forces, twists) if times else []
    _say(f"{path}: {len(times)} cycle records, {len(samples)} poses at rest")
    # the cycle records carry the lengths as the drivers read them: with drives.length_offset
    robot = config.robot
    offsets = np.array([s.length_offset for s in config.drives.scalings_for(robot)])
    if len(samples) < 2:
        raise CalibrationError(f"{path}: {len(samples)} poses at rest: nothing to calibrate")
    return offsets, samples


def _write_new(path: Path, robot: dict[str, Any], calibration: Calibration) -> None:
    now = datetime.datetime.now().isoformat(timespec="seconds")
    header = (
        f"# calibrated by cdprd calibrate on {now}"
        f" from {len(calibration.poses)} poses: residual RMS {calibration.residual_rms * 1e3:.4f}"
        f" mm, condition {calibration.condition:.3g}\n"
    )
    with open(path, "x") as f:  # never overwrites
        f.write(header)
        yaml.safe_dump(robot, f, sort_keys=False)


def _store_offsets(config: DaemonConfig, calibration: Calibration, robot_file: Path) -> str | None:
    """The calibrated offsets as the stored state (None: no state_dir)."""
    from daemon.service.calibration_state import (
        new_state,
        robot_identity,
        save_state,
        state_path,
    )

    if config.state_dir is None:
        return None
    path = state_path(config.state_dir, config.robot.name)
    # the offsets belong to the corrected robot file, as the daemon will read it
    identity = robot_identity(Robot.from_yaml(robot_file), config.drives)
    state = new_state(
        config.robot.name,
        identity,
        calibration.offsets.tolist(),
        f"calibrate (robot file {robot_file})",
    )
    try:
        save_state(path, state)
    except OSError as exc:
        _say(f"warning: offsets not stored in {path}: {exc}")
        return None
    return str(path)


def _print_report(report: dict[str, Any], calibration: Calibration) -> None:
    std = report["predicted_std"]
    print(f"corrected robot file: {report['robot_file']}")
    print(
        f"fit: {report['poses']} poses (of {report['planned']}), residual RMS "
        f"{report['residual_rms_mm']:.4f} mm, max {report['residual_max_mm']:.4f} mm"
    )
    scale = report["scale"]
    if scale["reference"] is None:
        print(f"scale: none (--no-scale), the drums' mean radius the file's: {scale['cost']}")
    else:
        print(
            f"scale: {scale['reference']} measured {scale['measured_m']:.4f} m, fitted "
            f"{scale['fitted_m']:.4f} m: the fit scaled x{scale['factor']:.6f}"
        )
    sv = report["singular_values"]
    print(
        f"identification Jacobian (poses eliminated, columns scaled): {sv['count']} singular "
        f"values {sv['smallest']:.3g} .. {sv['largest']:.3g}, condition {report['condition']:.3g}"
    )
    print(
        "predicted std at 10 um length noise: " + ", ".join(f"{k} {v:.3g}" for k, v in std.items())
    )
    print(f"EA: {calibration.stiffness_scale:.4f} x the file's")
    print("offsets (m): " + " ".join(f"{x:.5f}" for x in calibration.offsets))
    print("drum radius scales: " + " ".join(f"{x:.6f}" for x in calibration.drum_radius_scale))
    print(f"offsets stored: {report['offsets_stored'] or 'no (no state_dir): set them by homing'}")
    print(f"took {report['seconds']:.1f} s")
