"""`cdprd tune`: identify ONE winch's single-actuator model and propose gains (paper §4).

    cdprd tune --config FILE --sim [--drive K] [--load-mass KG | --clamped [--preload N]]
               [--amplitude N] [--duration S] [--travel M] [--json]

Drives cable K's drive through the config's driver in torque mode, the winch carrying
the passive load named (a hanging mass, none, or the drum clamped), with a bounded PRBS
experiment (tuning.experiment: never more than --amplitude from the holding force;
abort and brake on a drive fault, slack cable, length or force limit, naming it); fits
Assumption 1's m0, k0 and force lag (tuning.identify); designs PID gains checked over
m in [m0, 1.5 x the robot's largest modal mass] at the measured latency
(tuning.gain_design); prints the actuator block for the robot file and the controller
section.  --sim runs it against the simulator's one-winch rig (sim.rig with the config's
sim.plant: its mismatch and actuator model are the TRUE winch), the drive's CAN frames
exchanged in simulated time.

--json prints one object: drive, load {mass, clamped, hold}, experiment {seconds,
frames, samples, abort}, model {m0, k0, lag, cable_damping, confidence, residual_rms,
response_rms}, actuator (the robot file's block), actuator_model (sim.plant.actuator),
gains {kp, ki, kd, derivative_filter, bandwidth, ok, modal_mass_range, modal_loops
[{mass, settling_time, overshoot, poles}]}, controller (the config section).
Exit 0 on success, 3 when the experiment aborted (the drive was braked), 1 on a bad
config or request.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import yaml

from cdpr import ConfigError
from daemon.cli.analyze_cmd import _clean
from daemon.cli.run_cmd import load_checked, report

if TYPE_CHECKING:
    from tuning.gain_design import Design
    from tuning.winch_tune import Request, Run

ABORTED = 3


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "tune", help="identify one winch (Assumption 1) and propose gains (paper §4)"
    )
    p.add_argument("--config", required=True, help="daemon config YAML")
    p.add_argument("--sim", action="store_true", help="the simulator's one-winch rig")
    p.add_argument("--drive", type=int, default=0, help="cable index of the winch (default 0)")
    load = p.add_mutually_exclusive_group()
    load.add_argument("--load-mass", type=float, default=0.0, help="hanging mass, kg (0: none)")
    load.add_argument("--clamped", action="store_true", help="the drum's cable clamped")
    p.add_argument("--preload", type=float, default=100.0, help="clamped: pretension, N")
    p.add_argument("--amplitude", type=float, default=20.0, help="largest |f_c - hold|, N")
    p.add_argument("--duration", type=float, default=20.0, help="excitation time, s")
    p.add_argument("--travel", type=float, default=0.1, help="largest length excursion, m")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tuning.experiment import Plan
    from tuning.gain_design import design
    from tuning.winch_tune import Request, identify_simulated, load_of, plan_for
    from tuning.workspace_analysis import analyse

    try:
        config = load_checked(args.config)
    except ConfigError as exc:
        report(exc)
        return 1
    if not args.sim:
        print("error: only --sim is implemented so far (no real-time bus path)", file=sys.stderr)
        return 1
    from daemon.cli.simulated import sim_section

    request = Request(
        drive=args.drive,
        load_mass=args.load_mass,
        clamped=args.clamped,
        preload=args.preload,
        amplitude=args.amplitude,
        duration=args.duration,
        travel=args.travel,
    )
    robot, rate = config.robot, config.controller.rate_hz
    try:
        plan: Plan = plan_for(robot, request, rate)
        plan.check(load_of(robot, request))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    say = _progress(args.json)
    say(
        f"tune: cable {args.drive} ({config.drives.protocol} node "
        f"{config.drives.nodes[args.drive]}), load {_load(request)}, amplitude "
        f"+-{plan.amplitude:g} N, {plan.duration:g} s PRBS of +-{plan.excitation:g} N"
    )
    result = identify_simulated(robot, config.drives, sim_section(config).plant, request, rate)
    say(f"experiment: {result.experiment_seconds:.1f} s, {result.frames} CAN frames")
    if result.abort is not None:
        say(f"ABORTED and braked: {result.abort}")
        if args.json:
            abort = {"drive": args.drive, "abort": result.abort.kind, "reason": str(result.abort)}
            print(json.dumps(abort))
        return ABORTED
    model = result.model
    assert model is not None
    say(f"fit: m0 {model.m0:.4g} kg, k0 {model.k0:.4g} N s/m, lag {model.lag * 1e3:.4g} ms")
    say("analysing the robot's modal masses (Lemma 1)")
    analysis = analyse(robot, config.controller, points_per_axis=3)
    modal = analysis.grid.mass_range
    latency = 0.0  # in simulated time the commands act at the sample's instant
    say("designing gains over the mass range")
    gains = design(robot, model, modal, latency, rate)
    out = _report(args.drive, request, result, gains, modal, rate)
    if args.json:
        print(json.dumps(_clean(out)))
    else:
        _print(out)
    return 0


def _report(
    drive: int, request: Request, result: Run, gains: Design, modal: tuple, rate: float
) -> dict[str, Any]:
    model = result.model
    assert model is not None
    return {
        "drive": drive,
        "load": {"mass": request.load_mass, "clamped": request.clamped},
        "experiment": {
            "seconds": result.experiment_seconds,
            "frames": result.frames,
            "samples": len(result.record.sample_t),
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
        },
        "actuator": {"m0": round(model.m0, 4), "k0": round(model.k0, 3)},
        "actuator_model": {"c": [round(model.lag, 6)]},
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
        f"+-{100 * c['lag']:.2g} %; residual {1e6 * m['residual_rms']:.3g} um RMS of a "
        f"{1e3 * m['response_rms']:.3g} mm response"
    )
    print("robot file, actuator block:")
    print(yaml.safe_dump({"actuator": out["actuator"]}, sort_keys=False).rstrip())
    print("simulator / analysis force lag (sim.plant.actuator):")
    print(yaml.safe_dump({"actuator": out["actuator_model"]}).rstrip())
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


def _progress(quiet: bool) -> Callable[[str], None]:
    """Progress lines: on stdout, or on stderr when stdout carries the JSON."""

    def say(line: str) -> None:
        print(line, file=sys.stderr if quiet else sys.stdout, flush=True)

    return say
