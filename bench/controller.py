"""Benchmark of the parallel-actuator controller on config/robots/reference8.yaml.

Prints per-call median and p99 (us) of the whole controller step (`step`, replaying the
measurements of a closed-loop figure-8 run at 500 Hz), of the tension distribution
methods (`tda_osqp`, `tda_osqp_shortcut`, `tda_closed_form`, from bench/tension.py), and
the closed-loop figures of the standard trajectory set (`tracking`): per trajectory RMS
/ max position and orientation error of the paper's controller, tension range, slack
events, the ratio of its RMS position error to the joint-space baseline's
(`baseline_ratio`), and the same run under model mismatch (plant mass +10 %, m0 -10 %, 5
um encoder noise), and without the command lead (`no_lead`, and `lead_ratio`: RMS with
the lead / without; `command_lead_s` the lead used), and with a payload (`payload10`:
+10 % mass, `payload30`: +30 % and the centre of mass 5 cm off; flight RMS and holding
RMS with the payload estimate on, `adaptation_off` beside); the step without the
payload estimate (`step_adaptation_off`, `step_ratio`); the inertia estimate on the
elastic cables (`inertia`: the platform's inertia 1.5x the file's and 2 kg hung off its
centre, holding 2 s and then turning about all three axes: the errors of the inertia's
diagonal in %, of its products in kg m^2 and of the mass, the flight's and the hold's
RMS with the inertia estimated and, under `inertia_off`, without; `inertia_latency`: the
same with the commands taking effect INERTIA_LATENCY s late, the controller told); and the
holding
robot's response
to a 50 N horizontal push (`disturbance`: peak error, 2 % settling time, the error left
after 20 s, whether the peak exceeds the daemon's default tracking-error bound, and
`braked`: that, or a controller fault; with the external wrench observer as configured,
and under `observer_off` without it), and to the same push ending after 0.5 s
(`disturbance_release`: the push's peak, the rebound the other way once it ends, and
the 2 % settling time from the release; tuning.disturbance.release_response).

    python bench/controller.py [--json] [--calls N] [--skip-tracking]
"""

from __future__ import annotations

import argparse
import json
import sys

import tension
from timing import REFERENCE8, per_call_us, print_timings

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from daemon.config import SafetyConfig
from tuning.comparison import inertia_figures, payload_figures
from tuning.comparison import standard_set_figures as tracking
from tuning.disturbance import release_response, step_response
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking

INERTIA_LATENCY = 5e-4  # s: the commands' latency of the `inertia_latency` figures


def step_us(robot: Robot, spec: ControllerSpec, calls: int) -> dict[str, float]:
    """Time ParallelController.step on the measurements of a closed-loop figure-8 run."""
    trajectory = STANDARD_SET["figure_eight"](robot)
    run = run_tracking(robot, trajectory, ParallelController(robot, spec), rate_hz=spec.rate_hz)
    rec = run.recording
    # each cycle's arguments ready before timing (reading the Recording costs ~1.5 us a
    # call); the time as a float, as the daemon passes it
    cycles = [
        (float(t), lengths, rates)
        for t, lengths, rates in zip(rec.t, rec.measured_lengths, rec.measured_rates, strict=True)
    ]
    start = rec.pose(0)
    controller = ParallelController(robot, spec)

    def replay(i: int) -> None:
        k = i % len(cycles)
        if k == 0:
            controller.reset(start)
            controller.follow(trajectory)
        controller.step(*cycles[k])

    return per_call_us(replay, calls, warm_up=0)


def tracking_with_payload(robot: Robot, spec: ControllerSpec) -> dict[str, dict]:
    """The standard set's figures with `payload10` and `payload30` added per trajectory
    (tuning.comparison.payload_figures)."""
    figures = tracking(robot, spec)
    for name, payload in payload_figures(robot, spec).items():
        figures[name].update(payload)
    return figures


def disturbance(robot: Robot, spec: ControllerSpec) -> dict:
    """A 50 N horizontal push on the holding robot, for 20 s (tuning.disturbance), with
    the external wrench observer as configured and, under `observer_off`, without it."""
    off = spec.disturbance_observer.model_copy(update={"enabled": False})
    figures = push_figures(robot, spec)
    figures["observer_off"] = push_figures(
        robot, spec.model_copy(update={"disturbance_observer": off})
    )
    return figures


def push_figures(robot: Robot, spec: ControllerSpec) -> dict[str, float | bool | str]:
    f = step_response(robot, spec, wrench=(50.0, 0.0, 0.0, 0.0, 0.0, 0.0), duration=20.0)
    bound_mm = SafetyConfig().tracking_error_position * 1e3
    return {
        "push_n": 50.0,
        "peak_mm": round(f.peak_mm, 3),
        "settle_s": round(f.settle_s, 3),
        "final_mm": round(f.final_mm, 3),
        "fault": f.fault,
        "exceeds_tracking_bound": f.peak_mm > bound_mm,  # the daemon would brake
        "braked": bool(f.fault) or f.peak_mm > bound_mm,
    }


def release_figures(robot: Robot, spec: ControllerSpec) -> dict[str, float | str]:
    """The 50 N push from 0.5 s to 1.0 s, then let go (tuning.disturbance)."""
    f = release_response(robot, spec, wrench=(50.0, 0.0, 0.0, 0.0, 0.0, 0.0), end=1.0)
    return {
        "push_n": 50.0,
        "push_s": 0.5,
        "peak_mm": round(f.peak_mm, 3),
        "rebound_mm": round(f.rebound_mm, 3),
        "settle_s": round(f.settle_s, 3),
        "fault": f.fault,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--calls", type=int, default=5000, help="timed controller steps")
    parser.add_argument("--skip-tracking", action="store_true", help="timings only")
    args = parser.parse_args(argv)

    robot = Robot.from_yaml(REFERENCE8)
    spec = ControllerSpec()
    results: dict[str, dict] = {"step": step_us(robot, spec, args.calls)}
    # the same replay without the payload estimate, in the same run (the
    # estimate's work must leave the step's median within 1.15x)
    fixed = spec.model_copy(
        update={"adaptation": spec.adaptation.model_copy(update={"enabled": False})}
    )
    results["step_adaptation_off"] = step_us(robot, fixed, args.calls)
    results["step_ratio"] = round(
        results["step"]["median_us"] / results["step_adaptation_off"]["median_us"], 3
    )
    results.update(tension.measure(robot, calls=max(args.calls, 2000)))
    if not args.skip_tracking:
        results["tracking"] = tracking_with_payload(robot, spec)
        results["command_lead_s"] = ParallelController(robot, spec).lead
        results["disturbance"] = disturbance(robot, spec)
        results["disturbance_release"] = release_figures(robot, spec)
        results["inertia"] = inertia_figures(robot, spec)
        results["inertia_latency"] = inertia_figures(robot, spec, INERTIA_LATENCY)
    if args.json:
        print(json.dumps(results))
        return 0
    timed = ("step", "step_adaptation_off", "tda_osqp", "tda_osqp_shortcut", "tda_closed_form")
    print_timings({name: results[name] for name in timed})
    print(f"step median with / without the payload estimate: {results['step_ratio']:.3f}")
    for name, f in results.get("tracking", {}).items():
        print(
            f"{name:14s} rms {f['rms_mm']:.3f} mm  max {f['max_mm']:.3f} mm  "
            f"rms {f['rms_deg']:.3f} deg  max {f['max_deg']:.3f} deg  "
            f"tension {f['min_tension']:.0f}-{f['max_tension']:.0f} N  slack {f['slack_events']}  "
            f"baseline rms {f['baseline']['rms_mm']:.3f} mm (ratio {f['baseline_ratio']:.2f})  "
            f"mismatch rms {f['mismatch']['rms_mm']:.3f} mm max {f['mismatch']['max_mm']:.3f} mm  "
            f"no lead rms {f['no_lead']['rms_mm']:.3f} mm (ratio {f['lead_ratio']:.2f})"
        )
        for payload in ("payload10", "payload30"):
            p, off = f[payload], f[payload]["adaptation_off"]
            print(
                f"{'':14s} {payload}: rms {p['rms_mm']:.3f} mm hold {p['hold_mm']:.3f} mm  "
                f"(adaptation off: rms {off['rms_mm']:.3f} mm hold {off['hold_mm']:.3f} mm)"
            )
    for key in ("inertia", "inertia_latency"):
        if key not in results:
            continue
        i = results[key]
        print(
            f"{key}: diagonal error {i['diagonal_error_pct']} %  products "
            f"{i['products_error']:.4f} kg m^2  mass {i['mass_error_pct']:.2f} %  rms "
            f"{i['rms_mm']:.3f} mm hold {i['hold_mm']:.3f} mm (inertia off: rms "
            f"{i['inertia_off']['rms_mm']:.3f} mm hold {i['inertia_off']['hold_mm']:.3f} mm)"
        )
    if "disturbance" in results:
        d = results["disturbance"]
        for name, p in (("observer", d), ("observer off", d["observer_off"])):
            print(
                f"50 N push, {name}: peak {p['peak_mm']:.2f} mm  settle {p['settle_s']:.2f} s  "
                f"exceeds bound {p['exceeds_tracking_bound']}  braked {p['braked']}"
            )
        r = results["disturbance_release"]
        print(
            f"50 N push for 0.5 s, then let go: peak {r['peak_mm']:.2f} mm  rebound "
            f"{r['rebound_mm']:.2f} mm  settle {r['settle_s']:.2f} s from the release"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
