"""Flying reference8 when the robot file's cable stiffness is wrong.

For a true EA of 0.5, 0.6, 1, 1.5 and 2 times the robot file's, each standard trajectory
in lock-step, enabled at rest as the daemon does (tuning.stiffness): whether it flew or
would brake (and why), the RMS / max position error of the true platform, the stiffness
estimate after the fit at rest and at the end, and the largest FK residual.

    python bench/stiffness.py [--json]
"""

from __future__ import annotations

import argparse
import json

from timing import REFERENCE8

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from tuning.stiffness import stiffness_sweep


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="one JSON list of the runs")
    args = parser.parse_args(argv)
    runs = stiffness_sweep(Robot.from_yaml(REFERENCE8), ControllerSpec())
    if args.json:
        print(json.dumps(runs))
        return 0
    for run in runs:
        print(
            f"EA x{run['ea_factor']:<4g} {run['trajectory']:13s} "
            f"{'flew' if run['flew'] else 'BRAKED'}  RMS {run['rms_mm']:.3f} mm  "
            f"max {run['max_mm']:.3f} mm  estimate {run['estimate_at_rest']:.3f} -> "
            f"{run['estimate_end']:.3f}  FK residual <= {run['max_fk_residual_mm']:.4f} mm"
            + (f"  ({run['fault']})" if run["fault"] else "")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
