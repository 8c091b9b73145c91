"""Benchmark of the tension distribution F on config/robots/reference8.yaml.

Prints per-call median and p99 in microseconds of OsqpTensionSolver.solve (`tda_osqp`,
OSQP on every cycle, warm-started from the previous one; `tda_osqp_shortcut`, the
default, which skips OSQP when the equality-constrained optimum already meets every
bound) and ClosedFormTensionSolver.solve (`tda_closed_form`) along a smooth path sampled
at 1 kHz: the inputs (Λ, τ, f_b, f0) come from the model at each sample, as in the
control cycle. Also reports the share of feasible cycles, of cycles with an active
bound, and OSQP's median iterations.

    python bench/tension.py [--json] [--calls N] [--t-ref NEWTONS]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from timing import REFERENCE8, per_call_us

from cdpr import Pose, Robot
from cdpr.tension import ClosedFormTensionSolver, OsqpTensionSolver, TensionLimits

Inputs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def path_inputs(robot: Robot, samples: int, rate: float = 1000.0) -> list[Inputs]:
    """(Λ, τ, f_b, f0) along a Lissajous path around home, `samples` cycles at `rate` Hz.

    Position and rotation vector are sums of sines (0.1-0.2 m, 0.08-0.15 rad, 0.15-0.35 Hz);
    the twist and acceleration are their analytic derivatives (ω ≈ d(rotvec)/dt, close
    enough for small angles: these are benchmark inputs, not a trajectory).
    """
    amp = np.array([0.2, 0.15, 0.1, 0.1, 0.08, 0.15])
    freq = 2 * np.pi * np.array([0.25, 0.35, 0.2, 0.3, 0.2, 0.15])
    phase = np.array([0.0, 1.0, 0.5, 0.2, 0.0, 1.3])
    home = robot.home.position
    out = []
    for t in np.arange(samples) / rate:
        arg = freq * t + phase
        x = amp * np.sin(arg)
        twist = amp * freq * np.cos(arg)
        alpha = -amp * freq**2 * np.sin(arg)
        pose = Pose.from_rotvec(home + x[:3], x[3:])
        L = robot.jacobian(pose)
        M, mu = robot.dynamics(pose, twist)
        tau = M @ alpha + mu
        f0 = robot.m0 * (L @ alpha + robot.bias_accel(pose, twist))
        f_b = robot.k0 * (L @ twist)
        out.append((L, tau, f_b, f0))
    return out


def measure(
    robot: Robot, calls: int = 20000, t_ref: float | None = None
) -> dict[str, dict[str, float]]:
    """Per-call timings of both tension distribution methods along the 1 kHz path.

    Returns {"tda_osqp": {...}, "tda_closed_form": {...}}, each with median_us, p99_us,
    feasible_share and active_share (cycles with a tension within 1e-6 N of a bound);
    tda_osqp also has iterations_median.
    """
    limits = TensionLimits.from_robot(robot, t_ref)
    inputs = path_inputs(robot, calls)
    results: dict[str, dict[str, float]] = {}
    for name, solver in (
        ("tda_osqp", OsqpTensionSolver(limits, interior_shortcut=False)),
        ("tda_osqp_shortcut", OsqpTensionSolver(limits)),
        ("tda_closed_form", ClosedFormTensionSolver(limits)),
    ):
        answers = [solver.solve(*args) for args in inputs]  # also the warm-up of the caches
        # timed in path order: each solve warm-starts from the previous sample's
        r: dict[str, float] = dict(per_call_us(lambda i, s=solver: s.solve(*inputs[i]), calls))
        r["feasible_share"] = round(float(np.mean([a.feasible for a in answers])), 4)
        r["active_share"] = round(_active_share(answers, inputs, limits), 4)
        if name.startswith("tda_osqp"):
            r["iterations_median"] = float(np.median([a.iterations for a in answers]))
        results[name] = r
    return results


def _active_share(answers: list, inputs: list[Inputs], limits: TensionLimits) -> float:
    active = 0
    for a, (_, _, f_b, f0) in zip(answers, inputs, strict=True):
        g = f0 + f_b
        lo = np.maximum(limits.t_min, g - limits.force_max)
        hi = g + limits.force_max
        active += a.feasible and bool(np.any((a.tensions < lo + 1e-6) | (a.tensions > hi - 1e-6)))
    return active / len(answers)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--calls", type=int, default=20000, help="timed calls (path samples)")
    parser.add_argument(
        "--t-ref", type=float, default=None, help="reference tension in N (default mid-range)"
    )
    args = parser.parse_args(argv)

    results = measure(Robot.from_yaml(REFERENCE8), args.calls, args.t_ref)
    if args.json:
        print(json.dumps(results))
    else:
        for name, r in results.items():
            extra = f"   iterations {r['iterations_median']:g}" if "iterations_median" in r else ""
            print(
                f"{name:18s} median {r['median_us']:7.2f} us   p99 {r['p99_us']:7.2f} us   "
                f"feasible {r['feasible_share']:.1%}   active bound {r['active_share']:.1%}" + extra
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
