"""`cdprd tune`: identify ONE winch's single-actuator model and propose gains (paper §4).

    cdprd tune --config FILE [--sim [--lockstep]] [--drive K]
               [--load-mass KG | --clamped [--preload N]]
               [--amplitude N] [--duration S] [--travel M] [--json] [--plot PNG]
               [--check-loads KG,KG,...]

Drives cable K's drive through the config's driver in torque mode, the winch carrying
the passive load named (a hanging mass, none, or the drum clamped), with a bounded PRBS
experiment (tuning.experiment: never more than --amplitude from the holding force;
abort and brake on a drive fault, slack cable, length or force limit, lost feedback or
bus, naming it); fits Assumption 1's m0, k0 and force lag (tuning.identify); designs
PID gains checked over m in [m0, 1.5 x the robot's largest modal mass] at the measured
loop latency (tuning.gain_design); prints the actuator block for the robot file and the
controller section.

Without --sim it runs in real time on the bus the config's `can:` section names
(hardware, or `python -m sim_bus` with a `sim.rig` section as a separate process over
socketcand) through the daemon's bus port, timer and driver (daemon.cli.tune_bus), at
the daemon core's scheduling (`realtime:`).  --sim runs the same in real time against
the in-process simulator's one-winch rig (sim.rig from the request, the config's
sim.robot and sim.plant: the true robot file, its mismatch and actuator model are the
TRUE winch); --sim --lockstep exchanges the drive's CAN frames with the same winch in
simulated time instead (fast, deterministic).

--json prints one object: drive, load {mass, clamped}, experiment {seconds, frames,
samples, latency, transit, abort}, model {m0, k0, lag, cable_damping, confidence,
residual_rms, response_rms, friction, residual_correlation, misfit}, actuator (the robot
file's block; its friction where the fit found at least 0.2 N), actuator_model
(sim.plant.actuator), friction (sim.plant.friction), gains {kp, ki, kd,
derivative_filter, bandwidth, ok, modal_mass_range, modal_loops [{mass, settling_time,
overshoot, poles}]}, controller (the config section), plot (the --plot
file), checks (--check-loads: per load {load, mass, settling_time, overshoot,
predicted_settling_time, predicted_overshoot, abort}). After an abort of the
identification: {drive, abort, reason}.
--plot PNG draws the data, the fit and the closed-loop poles across the mass range
(tuning.tune_plot).  --check-loads 0,5,10 flies the proposed gains on the winch through
a step of the length reference with each load hung (tuning.load_check; on the bus the
user hangs each and presses Enter) and sets the measured settling time and overshoot
against the identified model's; exit 3 if one aborted.
Exit 0 on success (also where the fit's residual says the model misses part of the
dynamics: a warning says so, tuning.identify), 3 when the experiment aborted (the drive
was braked), 1 on a bad config or request.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from cdpr import ConfigError
from daemon.cli.exit_codes import EXIT_ABORTED, EXIT_OK
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.run_cmd import load_checked, report
from daemon.config import DaemonConfig
from daemon.process.app import close_bus, open_bus
from daemon.process.realtime import realtime

if TYPE_CHECKING:
    from cdpr import Robot
    from sim_bus.plant.config import PlantConfig
    from tuning.experiment import Abort, WinchExperiment
    from tuning.gain_design import Design
    from tuning.identify import Identified
    from tuning.load_check import CheckResult
    from tuning.winch_tune import Request, Run


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "tune", help="identify one winch (Assumption 1) and propose gains (paper §4)"
    )
    p.add_argument("--config", required=True, help="daemon config YAML")
    p.add_argument("--sim", action="store_true", help="the simulator's one-winch rig")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="with --sim: exchange the frames in simulated time (fast, deterministic)",
    )
    p.add_argument("--drive", type=int, default=0, help="cable index of the winch (default 0)")
    load = p.add_mutually_exclusive_group()
    load.add_argument("--load-mass", type=float, default=0.0, help="hanging mass, kg (0: none)")
    load.add_argument("--clamped", action="store_true", help="the drum's cable clamped")
    p.add_argument("--preload", type=float, default=100.0, help="clamped: pretension, N")
    p.add_argument("--amplitude", type=float, default=20.0, help="largest |f_c - hold|, N")
    p.add_argument("--duration", type=float, default=20.0, help="excitation time, s")
    p.add_argument("--travel", type=float, default=0.1, help="largest length excursion, m")
    add_json_flag(p)
    p.add_argument("--plot", metavar="PNG", help="write the data, fit and gain check to PNG")
    p.add_argument(
        "--check-loads",
        type=_loads,
        metavar="KG,KG,...",
        help="fly the proposed gains through a step with each load hung (kg)",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tuning.experiment import Plan
    from tuning.gain_design import design
    from tuning.winch_tune import Request, load_of, plan_for
    from tuning.workspace_analysis import analyse

    if args.lockstep and not args.sim:
        reason = "--lockstep runs the simulator in simulated time: add --sim"
        print_error("usage", reason, args.json)
        return 1
    if args.plot and not Path(args.plot).resolve().parent.is_dir():
        print_error("usage", f"--plot {args.plot}: no such directory", args.json)
        return 1
    request = Request(
        drive=args.drive,
        load_mass=args.load_mass,
        clamped=args.clamped,
        preload=args.preload,
        amplitude=args.amplitude,
        duration=args.duration,
        travel=args.travel,
    )
    try:
        config = load_checked(args.config, _rig_edit(request) if args.sim else None)
    except ConfigError as exc:
        report(exc, args.json)
        return 1
    robot, rate = config.robot, config.controller.rate_hz
    try:
        plan: Plan = plan_for(robot, request, rate)
        plan.check(load_of(robot, request))
        config.drives.single(args.drive)
        simulated = _simulated(config) if args.lockstep else None
    except (ValueError, ConfigError) as exc:
        print_error("usage", str(exc), args.json)
        return 1
    say = _say
    where = "simulated time" if args.lockstep else ("in-process simulator" if args.sim else "bus")
    say(
        f"tune: cable {args.drive} ({config.drives.protocol} node "
        f"{config.drives.nodes[args.drive]}, {where}), load {_load(request)}, amplitude "
        f"+-{plan.amplitude:g} N, {plan.duration:g} s PRBS of +-{plan.excitation:g} N"
    )
    result = _experiment(args, config, request, simulated, say)
    say(f"experiment: {result.experiment_seconds:.1f} s, {result.frames} CAN frames")
    if result.abort is not None:
        say(f"ABORTED and braked: {result.abort}")
        if args.json:
            abort = {"drive": args.drive, "abort": result.abort.kind, "reason": str(result.abort)}
            print_result(abort, as_json=True)
        return EXIT_ABORTED
    model = result.model
    assert model is not None
    say(
        f"fit: m0 {model.m0:.4g} kg, k0 {model.k0:.4g} N s/m, lag {model.lag * 1e3:.4g} ms, "
        f"Coulomb friction {model.friction:.3g} N"
    )
    misfit = model.misfit()
    if misfit is not None:
        print(f"warning: {misfit}", file=sys.stderr)
    say("analysing the robot's modal masses (Lemma 1)")
    analysis = analyse(robot, config.controller, points_per_axis=3)
    modal = analysis.grid.mass_range
    say(f"designing gains over the mass range, loop latency {result.latency * 1e3:.3g} ms")
    gains = design(robot, model, modal, result.latency, rate)
    out = _report(args.drive, request, result, gains, modal, rate)
    aborted = False
    if args.check_loads:
        checks = _check_loads(args, config, request, simulated, model, gains, say)
        if checks is None:
            print_error("failed", "standard input ended before the next load was hung", args.json)
            return 1
        out["checks"] = [
            {**c._replace(abort=None)._asdict(), "abort": None if c.abort is None else str(c.abort)}
            for c in checks
        ]
        aborted = any(c.abort is not None for c in checks)
    if args.plot:
        from tuning.tune_plot import write_tune_plot
        from tuning.winch_tune import setup_for

        setup = setup_for(robot, request, result.record)
        try:
            write_tune_plot(Path(args.plot), result.record, setup, model, gains)
        except OSError as exc:
            reason = f"cannot write {args.plot}: {exc.strerror or exc}"
            print_error("not_written", reason, args.json)
            return 1
        out["plot"] = args.plot
    print_result(out, args.json, lambda: _print(out))
    return EXIT_ABORTED if aborted else EXIT_OK


def _loads(text: str) -> list[float]:
    try:
        loads = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected masses in kg, e.g. 0,5,10") from None
    bad = [m for m in loads if not 0.0 <= m < float("inf")]
    if bad:
        raise argparse.ArgumentTypeError(f"load {bad[0]:g} kg: a mass must be finite and >= 0")
    return loads


def _rig_edit(request: Request) -> Callable[[dict[str, Any]], None]:
    """--sim: the config's sim.rig becomes the winch and load the request names."""

    def edit(data: dict[str, Any]) -> None:
        sim = dict(data.get("sim") or {})
        rig = dict(sim.get("rig") or {}, drive=request.drive, clamped=request.clamped)
        if request.clamped:
            rig.update(load_mass=0.0, preload=request.preload)
        else:
            rig["load_mass"] = request.load_mass
        data["sim"] = {**sim, "rig": rig}

    return edit


def _experiment(
    args: argparse.Namespace,
    config: DaemonConfig,
    request: Request,
    simulated: tuple[Robot, PlantConfig] | None,
    say: Callable[[str], None],
) -> Run:
    """The identification experiment: in simulated time (--sim --lockstep: `simulated`,
    the true robot and the plant), or in real time on the in-process simulator's bus
    (--sim) or the bus the config names."""
    from tuning.experiment import WinchExperiment
    from tuning.winch_tune import finish, identify_simulated, load_of, plan_for

    robot, rate = config.robot, config.controller.rate_hz
    if simulated is not None:
        true, plant = simulated
        return identify_simulated(robot, config.drives, plant, request, rate, true=true)
    experiment = WinchExperiment(plan_for(robot, request, rate), load_of(robot, request))
    abort, frames = asyncio.run(_on_bus(config, request, args.sim, say, experiment))
    return finish(robot, request, experiment, abort, frames)


def _simulated(config: DaemonConfig) -> tuple[Robot, PlantConfig]:
    """--sim --lockstep: the robot the simulator builds its winch on (sim.robot, else the
    daemon's robot: sim_bus.config.true_base, as the in-process simulator has it) and the
    plant."""
    from daemon.cli.simulated import sim_section
    from sim_bus.config import true_base

    sim = sim_section(config)
    return true_base(sim, config.robot, config.base, config.source), sim.plant


def _check_loads(
    args: argparse.Namespace,
    config: DaemonConfig,
    request: Request,
    simulated: tuple[Robot, PlantConfig] | None,
    model: Identified,
    gains: Design,
    say: Callable[[str], None],
) -> list[CheckResult] | None:
    """--check-loads: the proposed gains flown through a step with each load hung (in
    the simulator: its rig with that load; on the bus: the user hangs it and presses
    Enter); None if standard input ends before a load is hung."""
    from tuning.load_check import check_result, step_check
    from tuning.winch_tune import run_simulated

    robot, rate = config.robot, config.controller.rate_hz
    results = []
    for mass in args.check_loads:
        hung, check = step_check(robot, request, rate, model, gains, mass)
        if simulated is not None:  # --sim --lockstep
            true, plant = simulated
            check.abort, _ = run_simulated(robot, config.drives, plant, hung, check, true=true)
        else:
            if not args.sim:
                say(f"hang {mass:g} kg on cable {request.drive} (0: none), then press Enter")
                if not sys.stdin.readline():
                    return None
            hung_config = load_checked(args.config, _rig_edit(hung)) if args.sim else config
            check.abort, _ = asyncio.run(_on_bus(hung_config, hung, args.sim, say, check))
        result = check_result(check, gains)
        results.append(result)
        say(_check_line(result))
    return results


def _check_line(c: CheckResult) -> str:
    if c.abort is not None:
        return f"check {c.load:g} kg: ABORTED and braked: {c.abort}"
    return (
        f"check {c.load:g} kg (m {c.mass:.3g} kg): settling {c.settling_time:.3g} s "
        f"(model {c.predicted_settling_time:.3g} s), overshoot {100 * c.overshoot:.1f} % "
        f"(model {100 * c.predicted_overshoot:.1f} %)"
    )


async def _on_bus(
    config: DaemonConfig,
    request: Request,
    sim: bool,
    say: Callable[[str], None],
    experiment: WinchExperiment,
) -> tuple[Abort | None, int]:
    """`experiment` in real time on the in-process simulator's bus (`sim`) or the bus
    the config names: its abort, and the frames."""
    from daemon.cli.tune_bus import BusExperiment
    from drivers.factory import protocol_driver

    robot, drives = config.robot, config.drives
    one = drives.single(request.drive)
    driver = protocol_driver(one, [drives.scalings_for(robot)[request.drive]])
    experiment.plan = dataclasses.replace(experiment.plan, stale_cycles=config.safety.stale_cycles)
    if sim:
        from daemon.cli.simulated import InProcessSimulator

        simulator = InProcessSimulator(config)
        buses, close = simulator.daemon_bus, simulator.close
        simulator.start()
    else:
        buses = open_bus(config)
        close = lambda: close_bus(buses)  # noqa: E731
    try:
        bus = buses[one.bus_names()[0]] if isinstance(buses, Mapping) else buses
        runner = BusExperiment(
            bus, driver, experiment, one.brake, config.safety.feedback_deadline, say
        )
        with realtime(config.realtime):  # the daemon core's scheduling, for the same cycle
            abort = await runner.run()
    finally:
        close()
    return abort, runner.frames


def _report(
    drive: int, request: Request, result: Run, gains: Design, modal: tuple, rate: float
) -> dict[str, Any]:
    from tuning.identify import FRICTION_FOUND

    model = result.model
    assert model is not None
    return {
        "drive": drive,
        "load": {"mass": request.load_mass, "clamped": request.clamped},
        "experiment": {
            "seconds": result.experiment_seconds,
            "frames": result.frames,
            "samples": len(result.record.sample_t),
            "latency": result.latency,
            "transit": result.record.transit,
            "abort": None,
        },
        "model": {
            "m0": model.m0,
            "k0": model.k0,
            "lag": model.lag,
            "cable_damping": model.cable_damping,
            "confidence": model.confidence,
            "residual_rms": model.residual_rms,
            "response_rms": model.response_rms,
            "friction": model.friction,
            "residual_correlation": model.residual_correlation,
            "misfit": model.misfit(),
        },
        "actuator": {
            "m0": round(model.m0, 4),
            "k0": round(model.k0, 3),
            # the robot file's friction, which the controller compensates, where found
            **({"friction": round(model.friction, 3)} if model.friction >= FRICTION_FOUND else {}),
        },
        "actuator_model": {"c": [round(model.lag, 6)]},
        "friction": {"coulomb": round(model.friction, 3)},
        "gains": {
            **gains.gains.model_dump(),
            "bandwidth": gains.bandwidth,
            "ok": gains.ok,
            "modal_mass_range": list(modal),
            "modal_loops": [
                {
                    "mass": loop.mass,
                    "settling_time": loop.settling_time,
                    "overshoot": loop.overshoot,
                    "poles": [[float(s.real), float(s.imag)] for s in loop.poles[:6]],
                }
                for loop in gains.modal
            ],
        },
        "controller": gains.controller_section(rate),
    }


def _print(out: dict[str, Any]) -> None:
    m = out["model"]
    c = m["confidence"]
    print(
        f"identified (95 % half-widths): m0 {m['m0']:.4g} kg +-{100 * c['m0']:.2g} %, "
        f"k0 {m['k0']:.4g} N s/m +-{100 * c['k0']:.2g} %, lag {1e3 * m['lag']:.4g} ms "
        f"+-{100 * c['lag']:.2g} %, Coulomb friction {m['friction']:.3g} N; residual "
        f"{1e6 * m['residual_rms']:.3g} um RMS of a {1e3 * m['response_rms']:.3g} mm response"
    )
    print("robot file, actuator block:")
    print(yaml.safe_dump({"actuator": out["actuator"]}, sort_keys=False).rstrip())
    print("simulator / analysis force lag and friction (sim.plant):")
    print(yaml.safe_dump({"actuator": out["actuator_model"], "friction": out["friction"]}).rstrip())
    print("the daemon's command timing (drives section; controller.command_lead auto):")
    print(f"  force_lag: {m['lag']:.4g}")
    g = out["gains"]
    lo, hi = g["modal_mass_range"]
    print(
        f"gains for m in [m0, 1.5 x {hi:.3g} kg] (modal masses {lo:.3g}..{hi:.3g} kg): "
        f"{'ok' if g['ok'] else 'NO candidate passed'}, bandwidth {g['bandwidth']:.3g} 1/s"
    )
    for loop in g["modal_loops"]:
        poles = ", ".join(f"{re:.3g}{im:+.3g}j" for re, im in loop["poles"][:3])
        print(
            f"  m {loop['mass']:.3g} kg: settling {loop['settling_time']:.3g} s, overshoot "
            f"{100 * loop['overshoot']:.1f} %, slowest poles {poles}"
        )
    print("controller section:")
    print(yaml.safe_dump({"controller": out["controller"]}, sort_keys=False).rstrip())


def _load(request: Request) -> str:
    if request.clamped:
        return f"clamped at {request.preload:g} N"
    return f"{request.load_mass:g} kg hanging" if request.load_mass else "none (free drum)"


def _say(line: str) -> None:
    """A line of what the command does, on stderr: stdout carries the result alone."""
    print(line, file=sys.stderr, flush=True)
