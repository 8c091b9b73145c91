"""The controller gains' stability check of `cdprd check-config` and `cdprd run`.

Lemma 1 at the home pose: the robot's small-signal error along each eigenvector obeys
the single-actuator loop with effective mass m_i (a modal mass), so every modal mass
must be stabilised by the controller's law and gains discretised at controller.rate_hz,
with the drives' force lag (drives.force_lag).  The loop model is `cdprd analyze`'s
(tuning.workspace_analysis.rig_for, tuning.analysis.Rig), imported when the check runs
(the documented exception of analyze_cmd); the check takes a fraction of analyze's time:
the stable range from m0 (analyze's "largest stable mass", the same number) from the
loop's poles alone, and the latency tolerance over the home modal masses only, scanned
in quarter periods.

Timing: controller.command_lead moves where the reference and the feed-forward are
evaluated, not the feedback, so it is not in the small-signal loop.  The latency is: a
command computed from the sample at t_k acts from t_k + latency; the daemon sends it
when the feedback is in, at the latest safety.feedback_deadline of a period after the
cycle opened, so the loop must bear every latency up to that.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from cdpr import ConfigError
from cdpr.control_spec import DEFAULT_PID, ControllerSpec

if TYPE_CHECKING:
    from daemon.config import DaemonConfig
    from tuning.workspace_analysis import LatencyTolerance

LATENCY_STEP = 0.25  # periods: the latency scan's step (analyze: 0.05 over more masses)
ADVICE = (
    "change the gains or raise controller.rate_hz (`cdprd analyze --config {}` shows the "
    "modes and margins, `cdprd tune` designs gains)"
)


class GainCheck(NamedTuple):
    """The single-actuator loop of a daemon config against its home modal masses."""

    spec: ControllerSpec
    force_lag: float  # s
    m0: float  # kg: the lightest effective mass (the actuator's own)
    masses: NDArray[np.float64]  # the home pose's modal masses (kg, ascending)
    largest_stable_mass: float | None  # stable at every mass in [m0, this]; None: not m0
    stable_to_sweep_end: bool
    latency: LatencyTolerance  # over the home's finite modal masses
    deadline: float  # s: the latest the daemon's commands act after their sample

    @property
    def unstable_mode(self) -> int | None:
        """The first home mode (0-based) beyond the stable range; None: none."""
        edge = self.largest_stable_mass
        beyond = [i for i, m in enumerate(self.masses) if edge is None or not m <= edge]
        return beyond[0] if beyond else None

    @property
    def tolerates_deadline(self) -> bool:
        """Every command latency from 0 to the deadline keeps the home modes stable."""
        seconds = self.latency.seconds
        return seconds is not None and seconds >= self.deadline

    def summary(self) -> str:
        """check-config's line, for gains that passed the check (problem() is '')."""
        edge, seconds = self.largest_stable_mass, self.latency.seconds
        assert edge is not None and seconds is not None, "the gains failed the check"
        largest = float(np.max(self.masses))
        reach = f"modal masses up to {edge:.3g} kg"
        if self.stable_to_sweep_end:
            reach = f"every mass from m0 = {self.m0:g} kg to {edge:g} kg (the sweep's end)"
        delay = f"{1e3 * seconds:.3g} ms"
        if self.latency.limiting_mass is None:
            delay = f"at least {delay} (the scan's end)"
        return (
            f"controller stability: stable for {reach} (largest at home {largest:.3g} kg, "
            f"margin x{edge / largest:.2f}); tolerates {delay} of command delay (the "
            f"daemon's commands act within {1e3 * self.deadline:.3g} ms: "
            "safety.feedback_deadline)"
        )

    def figures(self) -> dict[str, object]:
        """check-config --json's figures of summary() (the same check, as numbers)."""
        pid = None if self.spec.state_space is not None else self.spec.pid or DEFAULT_PID
        return {
            "law": "pid" if pid is not None else "state_space",
            "pid": None if pid is None else pid.model_dump(),
            "m0": self.m0,
            "largest_stable_mass": self.largest_stable_mass,
            "stable_to_sweep_end": self.stable_to_sweep_end,
            "largest_modal_mass_at_home": float(np.max(self.masses)),
            "latency_tolerance_s": self.latency.seconds,
            "latency_scan_end": self.latency.limiting_mass is None,
            "deadline_s": self.deadline,
        }

    def problem(self) -> str:
        """What makes the loop unstable, naming the mode, rate and gains ('' if nothing)."""
        setting = (
            f"at {self.spec.rate_hz:g} Hz with {law(self.spec)} and drives.force_lag "
            f"{1e3 * self.force_lag:g} ms"
        )
        edge = self.largest_stable_mass
        mode = self.unstable_mode
        if mode is not None:
            reach = (
                f"unstable already at m0 = {self.m0:g} kg"
                if edge is None
                else f"stable for masses up to {edge:.3g} kg only"
            )
            return (
                f"mode {mode + 1} at home (modal mass {self.masses[mode]:.3g} kg) is unstable "
                f"{setting}: the single-actuator loop is {reach}"
            )
        if self.tolerates_deadline:
            return ""
        mass = self.latency.limiting_mass
        assert mass is not None and self.latency.seconds is not None  # stable at 0, see above
        which = int(np.argmin(np.abs(self.masses - mass)))
        return (
            f"mode {which + 1} at home (modal mass {mass:.3g} kg) goes unstable {setting} "
            f"when commands act {1e3 * self.latency.seconds:.3g} ms after their sample; the "
            f"daemon's commands act up to {1e3 * self.deadline:.3g} ms after it "
            "(safety.feedback_deadline of a period)"
        )


def check_gains(config: DaemonConfig) -> GainCheck:
    """The config's gains against its home modal masses (module docstring)."""
    from tuning.workspace_analysis import latency_tolerance, rig_for, stable_range

    robot, spec, lag = config.robot, config.controller, config.drives.force_lag
    rig = rig_for(robot, spec, force_lag=lag)
    masses = robot.modal_masses(robot.home)
    edge, to_end = stable_range(rig)
    finite = np.unique(masses[np.isfinite(masses)])
    latency = latency_tolerance(rig, finite, step=LATENCY_STEP)
    deadline = config.safety.feedback_deadline * spec.period
    return GainCheck(spec, lag, rig.actuator.m0, masses, edge, to_end, latency, deadline)


def stable_gains(config: DaemonConfig) -> GainCheck:
    """check_gains, or ConfigError naming the unstable mode, the rate and the gains."""
    advice = ADVICE.format(config.source)
    try:
        check = check_gains(config)
    except np.linalg.LinAlgError as exc:  # overflowing matrices: a time constant out of range
        raise ConfigError(
            f"{config.source}: controller: the single-actuator loop at "
            f"{config.controller.rate_hz:g} Hz with {law(config.controller)} cannot be "
            f"evaluated ({exc}); {advice}"
        ) from None
    problem = check.problem()
    if problem:
        raise ConfigError(f"{config.source}: controller: {problem}; {advice}")
    return check


def law(spec: ControllerSpec) -> str:
    """The controller's law and gains, in a line."""
    if spec.state_space is not None:
        return f"state-space ({len(spec.state_space.A)} states)"
    gains = spec.pid or DEFAULT_PID
    return f"pid kp {gains.kp:g} ki {gains.ki:g} kd {gains.kd:g}" + (
        f" filter {gains.derivative_filter:g} s" if gains.derivative_filter else ""
    )
