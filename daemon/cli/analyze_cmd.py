"""`cdprd analyze`: a robot's modal masses (Lemma 1), the modes they predict, and
whether the single-actuator gains cover them (the paper's claim 1).

    cdprd analyze --config FILE [--grid N] [--shrink F] [--json] [--plot DIR] [--progress]

FILE is a robot description (config/robots/*.yaml) or a daemon config with a `robot:`
key (a mapping, or a path relative to FILE) and an optional `controller:` section; the
gains are that section's, else the defaults (DEFAULT_PID).  The analysis itself is
tuning.workspace_analysis: this module only loads, prints, writes JSON and plots.

Importing sim_bus from daemon is a documented exception (DESIGN §2, like `demo`): the
analysis runs the simulator's single-actuator rig.  It is imported when the command
runs, so the daemon's other commands never load it.

--json prints one object with the keys: robot, config, controller {law, gains,
rate_hz, discretisation, model_at}, rig {m0, k0, cable_length, cable_stiffness,
preload}, home (a pose: position, quaternion, feasible, reason, detail, modal_masses,
internal_stiffness, modes [{mass, stable, frequency_hz, damping, resonance_hz,
resonance_damping, settling_time, overshoot, poles}]), grid {points_per_axis, shrink,
low, high, total, analysed, skipped {rank, lengths, tensions}, modal_mass_range,
settling_time_range, max_overshoot, all_stable, points [poses, modes without poles]},
robustness {m0, sweep_end, largest_stable_mass, stable_to_sweep_end,
largest_modal_mass, covers_workspace, sweep [{mass, stable, spectral_radius,
settling_time, overshoot}]}, latency_tolerance {seconds, periods, limiting_mass,
searched_to, mass_range}, plots [files].  Non-finite numbers are null.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from cdpr import ConfigError, Robot
from cdpr.control_spec import DEFAULT_PID, ControllerSpec, parse_controller
from cdpr.controller import static_tensions, tension_solver
from cdpr.description import load_yaml
from daemon.cli.gain_check import law
from daemon.cli.output import add_json_flag, plain, print_error, print_result
from daemon.cli.progress import add_progress_flag, progress_line
from daemon.cli.run_cmd import report

if TYPE_CHECKING:
    from tuning.workspace_analysis import Analysis, PoseAnalysis, PredictedMode

PLOTS = ("modal_masses.png", "modes_vs_mass.png", "robot-3d.png", "workspace.png")


def add_parser(subparsers: Any) -> None:
    """Register `analyze` on the cdprd subcommand parsers."""
    p = subparsers.add_parser(
        "analyze", help="modal masses, predicted modes and gain robustness of a robot"
    )
    p.add_argument("--config", required=True, help="robot YAML, or a daemon config with robot:")
    p.add_argument("--grid", type=_grid_points, default=5, help="grid points per axis (2-20)")
    p.add_argument(
        "--shrink", type=_fraction, default=0.5, help="grid box: fraction of the anchors' box"
    )
    add_json_flag(p)
    p.add_argument("--plot", metavar="DIR", help="write PNG plots into DIR")
    add_progress_flag(p)


def run(args: argparse.Namespace) -> int:
    """Analyse, print (text or JSON), plot; 1 with a message on a bad config or plot dir."""
    from tuning.workspace_analysis import analyse

    try:
        robot, spec, force_lag = load_config(args.config)
    except ConfigError as exc:
        report(exc, args.json)
        return 1
    with progress_line("grid", args.progress) as line:
        analysis = analyse(
            robot, spec, args.grid, args.shrink, progress=line.count, force_lag=force_lag
        )
    try:
        plots = (
            write_plots(analysis, Path(args.plot), robot, spec, args.config) if args.plot else []
        )
    except OSError as exc:
        reason = f"cannot write plots to {args.plot}: {exc.strerror or exc}"
        print_error("not_written", reason, args.json)
        return 1
    print_result(
        to_json(analysis, args.config, args.shrink, plots),
        args.json,
        lambda: print_text(analysis, plots, sys.stdout),
    )
    return 0


def load_config(path: str | Path) -> tuple[Robot, ControllerSpec, float | None]:
    """The robot and controller settings of a robot file or a daemon config, and the
    drives' force lag (s) of a daemon config with a `drives:` section (then checked whole,
    as `run` reads it; None: the simulator's actuator model's lag)."""
    path = Path(path)
    data = load_yaml(path)
    if not (isinstance(data, dict) and "robot" in data):
        return Robot.from_dict(data, source=str(path)), ControllerSpec(), None
    if "drives" in data:
        from daemon.config import load_config as load_daemon_config

        config = load_daemon_config(path)
        return config.robot, config.controller, config.drives.force_lag
    loaded = Robot.from_reference(data["robot"], path.parent, source=str(path))
    return loaded, parse_controller(data.get("controller"), source=str(path)), None


# -- text ---------------------------------------------------------------------------


def print_text(a: Analysis, plots: list[str], out: TextIO) -> None:
    """The human-readable report."""
    out.write("\n".join(_text_lines(a, plots)) + "\n")


def _text_lines(a: Analysis, plots: list[str]) -> list[str]:
    spec, rig, grid, rob = a.spec, a.rig, a.grid, a.robustness
    act = rig.actuator
    lines = [
        f"robot {a.robot}: controller {law(spec)} at {spec.rate_hz:g} Hz "
        f"(model_at {spec.model_at})",
        f"rig: m0 {act.m0:g} kg, k0 {act.k0:g} N s/m, cable {rig.cable_length:.3f} m "
        f"(EA {rig.config.cable.stiffness:g} N), preload {rig.preload:.0f} N",
    ]
    home = a.home
    if home.feasible:
        lines.append(f"modal masses at home (Lemma 1, kg): {_masses(home.masses)}")
        lines.append("predicted modes at home (single actuator with load m_i):")
        lines += _mode_table(home)
    else:
        lines.append(f"home pose not analysed ({home.reason}): {home.detail}")
    if spec.model_at == "reference":
        lines.append(
            "note: model_at reference keeps the internal-tension stiffness (K_int/m) in the "
            "loop; the rig has none, so modes where it is not small against the controller's "
            "stiffness differ from these (they are those of model_at measured)"
        )
    lo, hi, n = grid.low, grid.high, grid.points_per_axis
    skipped = grid.skipped
    reasons = ", ".join(f"{k} {v}" for k, v in skipped.items())
    lines.append(
        f"workspace grid: {n} x {n} x {n} = {len(grid.points)} poses at the home orientation "
        f"in x [{lo[0]:.3f}, {hi[0]:.3f}] y [{lo[1]:.3f}, {hi[1]:.3f}] "
        f"z [{lo[2]:.3f}, {hi[2]:.3f}] m; {len(grid.feasible)} analysed, "
        f"{sum(skipped.values())} skipped ({reasons})"
    )
    if grid.feasible:
        mlo, mhi = grid.mass_range
        modes = [m for p in grid.feasible for m in p.modes]
        settle = [m.settling_time for m in modes]
        overshoot = 100 * max(m.overshoot for m in modes)
        lines.append(f"  modal masses over the grid: {mlo:.3g} to {mhi:.3g} kg")
        lines.append(
            f"  predicted settling times {min(settle):.3g} to {max(settle):.3g} s, overshoot "
            f"up to {overshoot:.1f} %, all stable: {_yes(all(m.stable for m in modes))}"
        )
    edge = rob.largest_stable_mass
    if edge is None:
        lines.append(f"robustness: the rig is unstable already at m0 = {act.m0:g} kg")
    elif rob.stable_to_sweep_end:
        lines.append(
            f"robustness: stable for every mass from m0 = {act.m0:g} kg to "
            f"{rob.sweep_end:g} kg (the sweep's end)"
        )
    else:
        lines.append(
            f"robustness: largest stable mass {edge:.3g} kg (stable from m0 = {act.m0:g} kg up "
            "to it)"
        )
    largest = a.largest_modal_mass
    claim = (
        f"claim 1 (the gains cover every modal mass found, up to {largest:.3g} kg): "
        f"{_yes(a.covers_workspace)}"
    )
    if a.covers_workspace and edge is not None and not rob.stable_to_sweep_end:
        claim += f" (margin x{edge / largest:.2f})"
    lines.append(claim)
    lines.append(_latency_line(a))
    lines += [f"wrote {name}" for name in plots]
    return lines


def _latency_line(a: Analysis) -> str:
    lat, period = a.latency, a.spec.period
    masses = f"{lat.masses.min():.3g} to {lat.masses.max():.3g} kg"
    if lat.seconds is None:
        return f"latency tolerance: none, the {lat.limiting_mass:.3g} kg loop is unstable as it is"
    line = (
        f"latency tolerance: stable for masses {masses} while the drives apply each command "
        f"up to {1e3 * lat.seconds:.3g} ms ({lat.periods(period):.2f} periods) after its sample"
    )
    if lat.limiting_mass is None:
        return line + " (the scan's end)"
    return line + f"; beyond, the {lat.limiting_mass:.3g} kg loop goes unstable first"


def _mode_table(p: PoseAnalysis) -> list[str]:
    rows = [
        "  mode  mass kg  dominant Hz  zeta  resonance Hz  zeta  settling s  overshoot %  "
        "K_int/m 1/s^2"
    ]
    for i, (m, k) in enumerate(zip(p.modes, p.internal_stiffness, strict=True)):
        rows.append(
            f"  {i + 1:4d}  {m.mass:7.3g}  {m.frequency_hz:11.3g}  {m.damping:4.2f}  "
            f"{m.resonance_hz:12.3g}  {m.resonance_damping:4.2f}  {m.settling_time:10.3g}  "
            f"{100 * m.overshoot:11.1f}  {k:13.4g}{'' if m.stable else '  UNSTABLE'}"
        )
    return rows


def _masses(masses: np.ndarray) -> str:
    return ", ".join("inf" if np.isinf(m) else f"{m:.3g}" for m in masses)


def _yes(flag: bool) -> str:
    return "yes" if flag else "NO"


# -- JSON ---------------------------------------------------------------------------


def to_json(a: Analysis, config: str, shrink: float, plots: list[str]) -> dict[str, Any]:
    """The analysis as plain JSON values (keys in the module docstring)."""
    spec, rig, grid, rob = a.spec, a.rig, a.grid, a.robustness
    gains = None if spec.state_space is not None else (spec.pid or DEFAULT_PID).model_dump()
    modes = [m for p in grid.feasible for m in p.modes]
    settle = [m.settling_time for m in modes]
    return plain(
        {
            "robot": a.robot,
            "config": str(config),
            "controller": {
                "law": "state_space" if spec.state_space is not None else "pid",
                "gains": gains,
                "rate_hz": spec.rate_hz,
                "discretisation": spec.discretisation,
                "model_at": spec.model_at,
            },
            "rig": {
                "m0": rig.actuator.m0,
                "k0": rig.actuator.k0,
                "cable_length": rig.cable_length,
                "cable_stiffness": rig.config.cable.stiffness,
                "preload": rig.preload,
            },
            "home": _pose_json(a.home, poles=True),
            "grid": {
                "points_per_axis": grid.points_per_axis,
                "shrink": shrink,
                "low": grid.low.tolist(),
                "high": grid.high.tolist(),
                "total": len(grid.points),
                "analysed": len(grid.feasible),
                "skipped": grid.skipped,
                "modal_mass_range": list(grid.mass_range) if grid.feasible else None,
                "settling_time_range": [min(settle), max(settle)] if settle else None,
                "max_overshoot": max((m.overshoot for m in modes), default=None),
                "all_stable": all(m.stable for m in modes),
                "points": [_pose_json(p, poles=False) for p in grid.points],
            },
            "robustness": {
                "m0": rig.actuator.m0,
                "sweep_end": rob.sweep_end,
                "largest_stable_mass": rob.largest_stable_mass,
                "stable_to_sweep_end": rob.stable_to_sweep_end,
                "largest_modal_mass": a.largest_modal_mass,
                "covers_workspace": a.covers_workspace,
                "sweep": [
                    {
                        "mass": loop.mass,
                        "stable": loop.stable,
                        "spectral_radius": loop.spectral_radius,
                        "settling_time": loop.settling_time,
                        "overshoot": loop.overshoot,
                    }
                    for loop in rob.sweep
                ],
            },
            "latency_tolerance": {
                "seconds": a.latency.seconds,
                "periods": a.latency.periods(spec.period),
                "limiting_mass": a.latency.limiting_mass,
                "searched_to": a.latency.searched_to,
                "mass_range": [a.latency.masses.min(), a.latency.masses.max()],
            },
            "plots": plots,
        }
    )


def _pose_json(p: PoseAnalysis, poles: bool) -> dict[str, Any]:
    return {
        **p.pose.as_dict(),
        "feasible": p.feasible,
        "reason": p.reason,
        "detail": p.detail,
        "modal_masses": p.masses.tolist(),
        "internal_stiffness": p.internal_stiffness.tolist(),
        "modes": [_mode_json(m, poles) for m in p.modes],
    }


def _mode_json(m: PredictedMode, poles: bool) -> dict[str, Any]:
    out = {k: v for k, v in m._asdict().items() if k != "poles"}
    if poles:
        out["poles"] = [[float(s.real), float(s.imag)] for s in m.poles]
    return out


# -- plots --------------------------------------------------------------------------


def write_plots(
    a: Analysis, directory: Path, robot: Robot, spec: ControllerSpec, config: str
) -> list[str]:
    """PNG files in `directory` (created): modal masses over the grid; poles and
    settling time against the effective mass with the grid's modal-mass range marked;
    the robot in 3-D at home with its static tensions; the workspace's slices at home
    (`cdprd workspace` on a 10 cm grid, from the file at `config`)."""
    import matplotlib

    from tuning.robot_plot import write_robot_3d

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    grid, rob = a.grid, a.robustness
    names = [str(directory / name) for name in PLOTS]

    fig = plt.figure(figsize=(12, 5))
    ax = fig.add_subplot(1, 2, 1)
    feasible = grid.feasible
    if feasible:
        masses = np.array([p.masses for p in feasible])
        for i in range(masses.shape[1]):
            ax.plot(masses[:, i], ".", label=f"m_{i + 1}")
        ax.set_yscale("log")
        ax.legend(fontsize="small")
    ax.set_xlabel("analysed grid pose")
    ax.set_ylabel("modal mass (kg)")
    ax.set_title(f"{a.robot}: modal masses (Lemma 1)")
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    if feasible:
        xyz = np.array([p.pose.position for p in feasible])
        sc = ax3.scatter(*xyz.T, c=[p.masses.max() for p in feasible], cmap="viridis")
        fig.colorbar(sc, ax=ax3, label="largest modal mass (kg)", shrink=0.7)
    skipped = [p.pose.position for p in grid.points if not p.feasible]
    if skipped:
        ax3.scatter(*np.array(skipped).T, marker="x", color="red", label="skipped")
        ax3.legend(fontsize="small")
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    fig.tight_layout()
    fig.savefig(names[0], dpi=100)
    plt.close(fig)

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 5))
    sweep_masses = np.array([loop.mass for loop in rob.sweep])
    vmin, vmax = np.log10(sweep_masses[[0, -1]])
    for loop in rob.sweep:
        poles = loop.poles[np.isfinite(loop.poles)]
        shade = np.full(poles.size, math.log10(loop.mass))
        pts = left.scatter(
            poles.real, poles.imag, c=shade, s=6, cmap="viridis", vmin=vmin, vmax=vmax
        )
    for mode in a.home.modes:
        left.plot(mode.poles.real, mode.poles.imag, "r+", ms=8)
    fig.colorbar(pts, ax=left, label="log10 effective mass (kg)")
    left.set_xscale("symlog", linthresh=1.0)
    left.set_xlabel("Re s (1/s)")
    left.set_ylabel("Im s (1/s)")
    left.set_title("closed-loop poles vs mass (+: home modes)")
    settle = np.array([loop.settling_time for loop in rob.sweep])
    right.semilogx(sweep_masses, np.where(np.isfinite(settle), settle, np.nan), "k.-")
    if feasible:
        lo, hi = grid.mass_range
        right.axvspan(lo, hi, color="tab:green", alpha=0.2, label="grid modal masses")
    if rob.largest_stable_mass is not None and not rob.stable_to_sweep_end:
        right.axvline(rob.largest_stable_mass, color="tab:red", label="largest stable mass")
    right.set_xlabel("effective mass m (kg)")
    right.set_ylabel("2 % settling time (s)")
    right.set_title("single actuator with load m")
    right.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(names[1], dpi=100)
    plt.close(fig)

    home = static_tensions(robot, tension_solver(robot, spec), robot.home)
    title = f"{a.robot} at home: static tensions"
    write_robot_3d(names[2], robot, robot.home, home, title=title)
    from daemon.cli.workspace_cmd import COARSE_STEP, coarse_map
    from tuning.workspace_map import plot_slices

    title = f"{a.robot}: capacity margin at home ({COARSE_STEP * 100:g} cm grid)"
    plot_slices(coarse_map(config), names[3], title)
    return names


def _grid_points(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--grid takes a whole number, got {text!r}") from None
    if not 2 <= n <= 20:
        raise argparse.ArgumentTypeError(f"--grid must be between 2 and 20, got {n}")
    return n


def _fraction(text: str) -> float:
    try:
        f = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shrink takes a number, got {text!r}") from None
    if not 0.0 < f <= 1.0:
        raise argparse.ArgumentTypeError(f"--shrink must be in (0, 1], got {f}")
    return f
