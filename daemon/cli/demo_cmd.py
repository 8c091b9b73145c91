"""`cdprd demo`: the daemon and its simulator, the robot flown over zenoh.

The simulator (reference8, eight CiA 402 drives by default) runs in a process of its
own on socket pairs (daemon.cli.simulated.ProcessSimulator: like real drives, it never
takes the control cycle's CPU); the daemon starts held, and a zenoh client on loopback
— the same client module a planner uses — enables it, lets it settle in its hold for a
second, and sends a figure-eight with a ±10° wobble.  At the end it prints the tracking
error of the SIMULATED platform (truth, not the daemon's estimate: the simulator's true
pose every 20 ms against the reference the controller followed at that instant), the
cable tensions, the cycle timing and how often this host held the simulator's process
up (its drives then answer late, and the figures show the host as much as the robot),
and optionally plots them.

--json prints one object on stdout (the live-view line goes to stderr): robot, cables,
protocol, rate_hz, zenoh, trajectory {shape, duration_s, peak_speed_m_s, wobble_deg},
tracking_error {definition, rms_mm, max_mm, orientation_rms_deg, orientation_max_deg},
tensions {min_n, max_n, slack_events}, cycle (the daemon's cycle statistics: cycles,
deadline_misses, overruns, bus_errors, and p50_us/p99_us/max_us of jitter, compute,
prepare and latency, feedback->command), simulator {definition, held_up,
latest_wake_up_ms, late_answers, slowest_answer_ms}, final_state, telemetry, plot,
drawing (the files written, or null).
A demo that ends not holding or off by RMS 5 mm or more exits 1 with its figures; one
that did not complete prints {"error": ...} and exits 1.
Like `analyze`, this command imports sim_bus (the documented exception, DESIGN §2).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import json
import os
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr import ConfigError, Pose
from cdpr.controller import ControlOutput
from cdpr.trajectory import Trajectory
from daemon.cli.exit_codes import EXIT_FAILED
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.run_cmd import add_interface_options, interface_edit, report
from daemon.config import DaemonConfig, load_config
from daemon.process.logsetup import configure_logging
from daemon.process.recording_files import FileLimits, Series
from daemon.service.service import Service

if TYPE_CHECKING:
    from tuning.tracking import TrackingFigures

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "config" / "reference8-cia402.yaml"
PEAK_SPEED = 0.5  # m/s: the figure-eight's
WOBBLE_DEG = 10.0  # its tilt, +-
# s the platform holds after enable before the trajectory goes out: the enable's own
# transient (the loop closing on the platform where the brake left it: up to ~0.3 mm,
# over in ~0.5 s) is then over.  Sent at once, its tail fell into the flight's first
# moments by however long the validation took, and the figure ranged 0.03-0.06 mm RMS.
SETTLE = 1.0
TRACKING_ERROR = (
    "the simulated platform's true pose (the simulator's, every 20 ms) against the "
    "reference the controller followed at the same instant, while the trajectory runs "
    f"(sent once the platform has held for {SETTLE:g} s after enable)"
)
SIMULATOR = (
    "held_up: the 20 ms windows of the flight in which the simulator's process woke 10 ms "
    "late or more (sim_bus.runner.HELD_UP): this host did not run it, and its drives "
    "answered that late, as real drives on processors of their own would not; "
    "late_answers: the SYNCs of the whole run (as the cycle's deadline_misses) whose "
    "answers left the simulator after the daemon's feedback deadline, each a deadline "
    "miss the simulator's process caused; slowest_answer_ms: the longest a SYNC waited "
    "there for its answers"
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser(
        "demo",
        help="the daemon and its simulator: enable and fly a figure-eight over zenoh",
        description=__doc__,
    )
    demo.add_argument("--config", default=str(DEFAULT_CONFIG), help="daemon config YAML")
    demo.add_argument("--plot", metavar="PNG", help="write a plot of the run")
    demo.add_argument("--log-level", default="error")
    add_interface_options(demo)
    add_json_flag(demo)
    demo.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Fly the demo and print its figures (text, or JSON with --json)."""
    try:
        configure_logging(args.log_level)
        config = _loopback_config(Path(args.config), interface_edit(args))
    except ConfigError as exc:
        report(exc, args.json)
        return EXIT_FAILED
    return asyncio.run(_demo(config, Path(args.config), args.plot, args.json))


def _loopback_config(
    path: Path, edit: Callable[[dict[str, Any]], None] | None = None
) -> DaemonConfig:
    """The config with zenoh on a free loopback port, so a running daemon is not hit
    (and then `edit`: the command line's --view and --record)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]

    def loopback(data: dict[str, Any]) -> None:
        zenoh = dict(data.get("zenoh") or {})
        zenoh.update(listen=[f"tcp/127.0.0.1:{port}"], connect=[], mode="peer", expose=False)
        data["zenoh"] = zenoh
        realtime = dict(data.get("realtime") or {})
        realtime.setdefault("cpus", sorted(os.sched_getaffinity(0))[:1])
        data["realtime"] = realtime
        if edit is not None:
            edit(data)

    return load_config(path, loopback)


async def _demo(config: DaemonConfig, path: Path, plot: str | None, as_json: bool) -> int:
    from daemon.cli.simulated import ProcessSimulator
    from tuning.scenarios import figure_eight

    trajectory = figure_eight(config.robot, PEAK_SPEED, WOBBLE_DEG)
    result: dict[str, Any] = {}
    sources: list[tuple[float, Any]] = []  # (from, what the controller followed)

    async def fly(service: Service) -> None:
        def record(t: float, out: ControlOutput) -> None:
            source = service.controller.source
            if not sources or sources[-1][1] is not source:
                sources.append((t, source))

        result["t0"] = service.t0
        service.cycle_listeners.append(record)
        endpoint = config.zenoh.listen_endpoints[0]
        result["client"] = await _client_flight(client, endpoint, trajectory)
        await asyncio.sleep(0.5)  # settle at the end pose
        result["stats"] = service.stats.summary()
        result["state"] = service.machine.state.value

    if config.view.enabled:
        view = config.view
        print(
            f"live view: ws://{view.host}:{view.port} (Foxglove: open a connection, then "
            "the layout config/foxglove-layout.json)",
            file=sys.stderr if as_json else sys.stdout,
            flush=True,
        )
    client = await _start_client()
    try:
        simulator = ProcessSimulator(config, path)
        code = await simulator.serve(after_start=fly)
    except (ConfigError, RuntimeError) as exc:
        print_error("failed", str(exc), as_json, prefix="demo")
        return EXIT_FAILED
    finally:
        if client.returncode is None:  # the daemon stopped before the flight
            client.kill()
            await client.wait()
    if "client" not in result:
        print_error("failed", "the flight did not complete", as_json, prefix="demo")
        return EXIT_FAILED
    samples = _truth_samples(simulator.truth, result["t0"], sources)
    start = result["client"]["start"]
    figures = _summary(samples, start, start + trajectory.duration)
    if figures is None:
        reason = "no control cycle while the trajectory ran"
        print_error("failed", reason, as_json, prefix="demo")
        return EXIT_FAILED
    held = _simulator_figures(simulator.truth, result["t0"], start, start + trajectory.duration)
    summary, lines = _report(config, result, figures, held, trajectory.duration)
    written: dict[str, str | None] = {"telemetry": None, "plot": plot, "drawing": None}
    if config.recording.telemetry:
        written["telemetry"] = str(_latest_recording(Path(config.recording.telemetry)))
    if plot:
        _plot(samples, Path(plot))
        written["drawing"] = str(_plot_3d(config, samples, Path(plot)))
    human = lines + _written_lines(written)
    print_result({**summary, **written}, as_json, lambda: print("\n".join(human)))
    ok = result["state"] == "hold" and figures.rms_mm < 5.0
    return code if ok else EXIT_FAILED


def _latest_recording(path: Path) -> Path:
    """The newest file recorded for `path` (each is named after the time it began)."""
    files = Series(path, FileLimits()).files()
    return files[-1] if files else path


async def _start_client() -> asyncio.subprocess.Process:
    """The planner's side, in a process of its own like any planner's: started before
    the daemon raises its priority (so it never shares it), it waits for its request
    (`_client_flight`)."""
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "daemon.cli.demo_flight",
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
    )


async def _client_flight(
    client: asyncio.subprocess.Process, endpoint: str, trajectory: Trajectory
) -> dict[str, Any]:
    """Have `client` fly `trajectory` through the daemon at `endpoint`: its result."""
    request = {"endpoint": endpoint, "trajectory": trajectory.as_dict(), "settle": SETTLE}
    out, _ = await client.communicate(json.dumps(request).encode())
    if client.returncode != 0:
        raise RuntimeError(f"the demo's client failed (exit code {client.returncode})")
    return json.loads(out)


def _truth_samples(
    truth: list[dict], t0: float, sources: list[tuple[float, Any]]
) -> list[tuple[float, Pose, Pose, list[float]]]:
    """(daemon time, reference, true pose, tensions) for each record of the simulator's
    truth log: its monotonic stamp less the daemon's clock origin `t0`, and the
    reference the controller followed at that instant (`sources`: each source from the
    cycle it was first followed)."""
    samples = []
    starts = [t for t, _ in sources]
    for record in truth:
        t = record["monotonic"] - t0
        k = bisect.bisect_right(starts, t) - 1
        if k < 0:
            continue
        q = record["quaternion"]
        pose = Pose(np.array(record["position"]), np.array([q["w"], q["x"], q["y"], q["z"]]))
        samples.append((t, sources[k][1].sample(t).pose, pose, record["tensions"]))
    return samples


def _simulator_figures(
    truth: list[dict], t0: float, start: float, end: float
) -> dict[str, Any]:
    """How the host held the simulator up between daemon times `start` and `end` (the
    truth log's latest_wake_up_ms; `t0`: the daemon's clock origin): HELD_UP's windows
    and the latest wake-up; and over the whole run, the SYNCs it answered after the
    daemon's deadline and the slowest answer (SIMULATOR defines them)."""
    from sim_bus.runner import HELD_UP as LATE

    late = [r["latest_wake_up_ms"] for r in truth if start <= r["monotonic"] - t0 <= end]
    return {
        "definition": SIMULATOR,
        "held_up": sum(1 for ms in late if ms >= LATE * 1e3),
        "latest_wake_up_ms": round(max(late, default=0.0), 1),
        "late_answers": sum(r["late_answers"] for r in truth),
        "slowest_answer_ms": round(max((r["slowest_answer_ms"] for r in truth), default=0.0), 2),
    }


def _summary(samples, t0: float, t1: float) -> TrackingFigures | None:
    """Tracking error of the true platform against the reference while tracking."""
    from tuning.tracking import tracking_figures

    window = [s for s in samples if t0 <= s[0] <= t1]
    if not window:
        return None
    return tracking_figures([s[1] for s in window], [s[2] for s in window], [s[3] for s in window])


def _report(
    config: DaemonConfig,
    result: dict[str, Any],
    f: TrackingFigures,
    held: dict[str, Any],
    duration: float,
) -> tuple[dict[str, Any], list[str]]:
    """The run's figures by key (--json), and the lines a person reads, each built
    beside its figures."""
    stats = result["stats"]
    endpoint = config.zenoh.listen_endpoints[0]
    summary = {
        "robot": config.robot.name,
        "cables": config.robot.n_cables,
        "protocol": config.drives.protocol,
        "rate_hz": config.controller.rate_hz,
        "zenoh": endpoint,
        "trajectory": {
            "shape": "figure-eight",
            "duration_s": duration,
            "peak_speed_m_s": PEAK_SPEED,
            "wobble_deg": WOBBLE_DEG,
        },
        "tracking_error": {
            "definition": TRACKING_ERROR,
            "rms_mm": f.rms_mm,
            "max_mm": f.max_mm,
            "orientation_rms_deg": f.rms_deg,
            "orientation_max_deg": f.max_deg,
        },
        "tensions": {
            "min_n": f.min_tension,
            "max_n": f.max_tension,
            "slack_events": f.slack_events,
        },
        "cycle": stats,
        "simulator": held,
        "final_state": result["state"],
    }
    lines = [
        f"cdprd demo: {config.robot.name}, {config.robot.n_cables} {config.drives.protocol} "
        f"drives on the simulator, {config.controller.rate_hz:g} Hz, zenoh on {endpoint}",
        f"figure-eight, {duration:.1f} s, {PEAK_SPEED:g} m/s peak, ±{WOBBLE_DEG:g} deg wobble: "
        "trajectory accepted over zenoh",
        f"tracking error (simulated platform vs reference, same instant): RMS {f.rms_mm:.2f} mm, "
        f"max {f.max_mm:.2f} mm, orientation RMS {f.rms_deg:.3f} deg",
        f"cable tensions: {f.min_tension:.0f} .. {f.max_tension:.0f} N, "
        f"slack events {f.slack_events}",
        f"cycle: {stats['cycles']} cycles, compute p50/p99 {stats['compute']['p50_us']:.0f}/"
        f"{stats['compute']['p99_us']:.0f} us, feedback->command p50/p99 "
        f"{stats['latency']['p50_us']:.0f}/{stats['latency']['p99_us']:.0f} us, "
        f"deadline misses {stats['deadline_misses']}, overruns {stats['overruns']}",
        f"simulator held up by this host in {held['held_up']} of the flight's 20 ms windows "
        f"(latest wake-up {held['latest_wake_up_ms']:.1f} ms late)"
        + (": the figures show the host as much as the robot" if held["held_up"] else ""),
        f"simulator answered {held['late_answers']} SYNCs after the feedback deadline "
        f"(slowest {held['slowest_answer_ms']:.2f} ms): deadline misses of this host's "
        "making, not the robot's",
        f"final state: {result['state']}",
    ]
    return summary, lines


def _written_lines(written: dict[str, str | None]) -> list[str]:
    """The files the run wrote, a line each."""
    lines = []
    if written["telemetry"]:
        lines.append(f"telemetry recorded to {written['telemetry']}")
    if written["plot"]:
        lines.append(f"plot written to {written['plot']}")
        lines.append(f"3-D view at the largest tension written to {written['drawing']}")
    return lines


def _plot(samples, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s[0] for s in samples])
    ref = np.array([s[1].position for s in samples])
    true = np.array([s[2].position for s in samples])
    tensions = np.array([s[3] for s in samples])
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(15, 4.5))
    ax1.plot(ref[:, 0], ref[:, 1], "k--", label="reference")
    ax1.plot(true[:, 0], true[:, 1], label="simulated platform")
    ax1.set(xlabel="x (m)", ylabel="y (m)", title="path", aspect="equal")
    ax1.legend()
    ax2.plot(t, np.linalg.norm(true - ref, axis=1) * 1e3)
    ax2.set(xlabel="t (s)", ylabel="position error (mm)", title="tracking error")
    ax3.plot(t, tensions)
    ax3.set(xlabel="t (s)", ylabel="tension (N)", title="cable tensions")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_3d(config: DaemonConfig, samples, path: Path) -> Path:
    """`<stem>-3d.png` beside `path`: the robot at the instant of the run's largest
    cable tension, with the reference path and the simulated platform's path."""
    from tuning.robot_plot import write_robot_3d

    worst = max(samples, key=lambda s: max(s[3]))
    drawing = path.with_name(f"{path.stem}-3d.png")
    write_robot_3d(
        drawing,
        config.robot,
        worst[2],
        worst[3],
        path=[s[2].position for s in samples],
        reference=[s[1].position for s in samples],
        title=f"{config.robot.name} at t = {worst[0]:.2f} s, largest tension {max(worst[3]):.0f} N",
    )
    return drawing
