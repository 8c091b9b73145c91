"""`cdprd calibrate`: identify the robot's geometry from redundant cable lengths
(DESIGN §15 step 5).

    cdprd calibrate --config FILE [--poses N] [--reach X Y Z] [--tilt RAD] [--dwell S]
                    [--average S]
                    [--output FILE] [--json]   + the client options (--prefix, --connect)
    cdprd calibrate --config FILE --from-recording RUN.mcap [--output FILE] [--json]

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
from daemon.cli.run_cmd import load_checked

if TYPE_CHECKING:
    from daemon.config import DaemonConfig
    from daemon.interface.client import CdprClient
    from tuning.calibration import Calibration, Sample

SPEED = 0.2  # m/s (and rad/s) of the moves between poses
MOVE_MIN = 1.5  # s: the shortest move
MIN_POSES = 8  # below this the command refuses before flying
DITHER = 2e-4  # m: the loop flown about each pose while its state is averaged
LEASE = 5.0  # s: the lease on the payload freeze and the observer hold (daemon.service.lease)
RENEW_PERIOD = 1.0  # s between its renewals while flying


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
    p.add_argument("--output", help="the corrected robot file (default: beside the old one)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--prefix", help="key prefix of the daemon (default: the only one)")
    p.add_argument(
        "--connect",
        help=f"zenoh endpoint of the daemon (default ${CONNECT_ENV}, else {DEFAULT_CONNECT})",
    )
    p.add_argument("--timeout", type=float, default=10.0, help="seconds per daemon request")
    p.set_defaults(handler=run)


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    try:
        config = load_checked(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.poses < MIN_POSES and args.from_recording is None:
        print(f"usage error: --poses: at least {MIN_POSES}", file=sys.stderr)
        return EXIT_USAGE
    average = args.dwell / 2 if args.average is None else args.average
    if not 0.0 < average <= args.dwell:
        print(f"usage error: --average: more than 0 s, at most --dwell ({args.dwell:g} s)",
              file=sys.stderr)  # fmt: skip
        return EXIT_USAGE
    args.average = average
    output = _output_path(config, args.output)
    if output.exists():
        print(f"error: {output} exists: not overwritten (give another --output)", file=sys.stderr)
        return EXIT_USAGE
    from daemon.interface.client import RequestError, UnreachableError

    started = time.perf_counter()
    try:
        if args.from_recording is not None:
            offsets, samples = _from_recording(config, Path(args.from_recording))
        else:
            offsets, samples = _fly(config, args)
        calibration = _solve(config.robot, offsets, samples)
    except UnreachableError as exc:
        print(f"error: no daemon reachable: {exc}", file=sys.stderr)
        return EXIT_UNREACHABLE
    except RequestError as exc:
        print(f"error: the daemon refused ({exc.code}): {exc.reason}", file=sys.stderr)
        return EXIT_FAILED
    except CalibrationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    seconds = time.perf_counter() - started
    from tuning.calibration import corrected_robot

    corrected = corrected_robot(config.robot, calibration)
    _write_new(output, corrected, calibration)
    stored = _store_offsets(config, calibration, output)
    report = {
        **calibration.report(),
        "robot_file": str(output),
        "offsets_stored": stored,
        "seconds": seconds,
    }
    if args.json:
        print(json.dumps(report))
    else:
        _print_report(report, calibration)
    return EXIT_OK


def _output_path(config: DaemonConfig, given: str | None) -> Path:
    if given is not None:
        return Path(given)
    raw = config.raw.robot
    source = config.path(raw) if isinstance(raw, str) else config.base / f"{config.robot.name}.yaml"
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return source.with_name(f"{source.stem}.calibrated-{stamp}.yaml")


def _solve(robot: Robot, offsets: np.ndarray, samples: list[Sample]) -> Calibration:
    from tuning.calibration import identify

    _say(f"solving: {len(samples)} poses")
    try:
        calibration = identify(robot, offsets, samples, progress=_say)
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


def _fly(config: DaemonConfig, args: argparse.Namespace) -> tuple[np.ndarray, list[Sample]]:
    from daemon.interface.client import CdprClient, default_connect
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
    with CdprClient(args.prefix, args.connect or default_connect(), timeout=args.timeout) as client:
        status = client.status()
        if status["state"] != "hold":
            raise CalibrationError(
                f"the daemon is {status['state']}: enable it (cdprd enable) at rest first"
            )
        offsets = np.array(status["offsets"]["values"], dtype=float)
        with _file_model(client, robot):
            return offsets, _record_poses(client, poses, args.dwell, args.average)


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
    client: CdprClient, poses: list[Pose], dwell: float, average: float
) -> list[Sample]:
    """Move slowly to each pose (a rest-to-rest trajectory at SPEED, not a goto at the
    trajectory limits: the model is not calibrated yet), wait, and average the state over
    the dither loop there (the module docstring); a pose the daemon refuses to go to (the
    way leaves the wrench set, say) is skipped."""
    from cdpr.trajectory import Trajectory, Waypoint
    from daemon.interface.client import RequestError
    from tuning.calibration import Sample

    rows: list[tuple[float, list[float], list[float]]] = []
    latest: list[Pose] = []
    lock = threading.Lock()

    def on_state(state: dict[str, Any]) -> None:
        if state.get("state") in ("hold", "tracking") and "pose" in state:
            q = state["pose"]["quaternion"]
            with lock:
                latest[:] = [Pose(state["pose"]["position"], (q["w"], q["x"], q["y"], q["z"]))]
                rows.append((time.monotonic(), state["lengths"], state["forces"]))

    samples = []
    subscriber = client.subscribe_state(on_state)
    try:
        here = _wait_for_pose(latest, lock)
        for k, target in enumerate(poses):
            error = liediff(here, target)
            distance = max(float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:])))
            move = max(MOVE_MIN, distance / SPEED)
            trajectory = Trajectory([Waypoint(0.0, here), Waypoint(move, target)])
            try:
                reply = client.send_trajectory(trajectory)
            except RequestError as exc:
                if exc.code != "rejected":
                    raise
                _say(f"flying: pose {k + 1} of {len(poses)} refused, skipped: {exc.reason}")
                continue
            time.sleep(float(reply["result"].get("duration", move)) + dwell - average)
            here = target
            with lock:
                rows.clear()
            _dither(client, target, average)
            time.sleep(average)
            with lock:
                recent = list(rows)
                rows.clear()
            if not recent:
                state = client.status()
                raise CalibrationError(
                    f"pose {k + 1}: no state at rest from the daemon ({state['state']}"
                    + (f": {state['fault']['message']}" if state.get("fault") else "")
                    + ")"
                )
            samples.append(
                Sample(
                    np.mean([r[1] for r in recent], axis=0),
                    np.mean([r[2] for r in recent], axis=0),
                )
            )
            _say(f"flying: pose {k + 1} of {len(poses)} recorded")
    finally:
        subscriber.undeclare()
    return samples


def _dither(client: CdprClient, pose: Pose, duration: float) -> None:
    """Send a loop of DITHER about `pose` (at rest there) lasting `duration`: through
    +-DITHER along each axis in turn and back, at rest at each corner (the daemon
    validates a transition's first segment as a trajectory of its own, which must end
    at rest).  If the daemon refuses it the platform stays at rest, averaged as it is."""
    from cdpr.trajectory import Trajectory, Waypoint
    from daemon.interface.client import RequestError

    steps = [np.zeros(3)] + [DITHER * sign * axis for sign in (1, -1) for axis in np.eye(3)]
    dt = duration / len(steps)
    rest = np.zeros(6)
    waypoints = [
        Waypoint(k * dt, Pose(pose.position + step, pose.quaternion_tuple), rest, rest)
        for k, step in enumerate(steps)
    ]
    try:
        client.send_trajectory(Trajectory([*waypoints, Waypoint(duration, pose)]))
    except RequestError as exc:
        if exc.code != "rejected":
            raise


def _wait_for_pose(latest: list[Pose], lock: threading.Lock, timeout: float = 5.0) -> Pose:
    """The first measured pose the daemon publishes."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with lock:
            if latest:
                return latest[0]
        time.sleep(0.05)
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
        f"fit: {report['poses']} poses, residual RMS {report['residual_rms_mm']:.4f} mm, "
        f"max {report['residual_max_mm']:.4f} mm"
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
