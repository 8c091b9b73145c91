"""Fit the paper's Assumption 1 single-actuator model to a torque experiment.

The model is the rig the simulator and `cdprd analyze` use (sim_bus.plant.rig): a drum
of effective mass m0, back-EMF k0 and a first-order force lag tau,

    tau f' + f = f_c - k0 l',    m0 l'' = f + t - F_c sgn(l'),

pulling through an elastic cable (EA from the robot file, damping D fitted) a passive
load of known mass (none, hanging, or clamped).  Linearised at rest, it predicts the
length l(t) from the command f_c(t) as sent: the commands are held from the moment they
left the host, and the prediction is read at each feedback sample's stamp, so the
loop's own delays are part of the data rather than of the model.  The Coulomb friction
F_c is a force against the drum's measured speed (smoothed, its sign softened as
cdpr.friction softens it), so the model stays linear in its input: left out, 2 N of it
made k0 three times too large with a tight-looking confidence.  scipy's least squares fits m0, k0,
tau, F_c (and D, a constant force bias and the starting length) to the measured
lengths; each parameter's confidence is 1.96 standard errors from the Jacobian at the
optimum, widened for the residual's lag-1 autocorrelation (an AR(1) residual's
effective sample count: white-residual errors said +-0.8 % for a k0 three times too
large); a residual that correlated is reported as a misfit (Identified.misfit):
indicative, not a guarantee.

With the drum clamped (m = inf) the drum only moves by the cable's stretch: m0 is read
from the frequency of the drum on the cable's spring, so it rests on the robot file's
EA; the cable's damping acts on the drum's rate just as k0 does (the two cannot be told
apart: the fit's Jacobian is singular along them), so D stays at the simulator's
default and k0 takes any difference; and a force bias only shifts the length, which
each segment's constant takes.  A free drum or a hanging mass gives k0 on its own.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, signal

from cdpr.description import ActuatorSpec
from cdpr.friction import friction_direction
from sim_bus.plant.config import ActuatorModelConfig, CableConfig, PlantConfig
from sim_bus.plant.rig import SingleActuatorRig
from tuning.experiment import Load

Array = NDArray[np.float64]
GRID = 5e-4  # s: the simulation grid of the prediction
NAMES = ("m0", "k0", "lag", "cable_damping", "bias", "friction")
SMOOTHING = 0.01  # s: the window (Savitzky-Golay, quadratic) of the measured speed
RANGE = 20.0  # the fitted m0, k0, lag and damping lie within this factor of the guess
FRICTION_GUESS = 0.1  # N: where the friction's fit starts (inside its bound, >= 0)
# N: a fitted friction this large is the winch's (frictionless simulated winches fit
# below 0.05 N), so `cdprd tune` writes it into the robot file's actuator block
FRICTION_FOUND = 0.2
# the lag-1 autocorrelation of the residual beyond which the fit is said to miss part of
# the dynamics: on the simulator's winches 0.03-0.77 without friction or noise (free,
# hanging, clamped), 0.92-0.96 with 0.5-2 N of Coulomb friction (fitted) or with force
# noise; white measurement noise alone gives ~0
MISFIT_CORRELATION = 0.9


class Identified(NamedTuple):
    """The fitted model: m0 (kg), k0 (N s/m), lag (s: Assumption 1's c_2), the cable's
    damping (N s per unit strain; None where not fitted: no load, or clamped), and per
    parameter the relative 95 % half-width; the RMS residual (m) against the RMS
    response (m)."""

    m0: float
    k0: float
    lag: float
    cable_damping: float | None
    confidence: dict[str, float]
    residual_rms: float
    response_rms: float
    samples: int
    bias: float = 0.0  # N: the constant force offset the fit found
    friction: float = 0.0  # N: the drum's Coulomb friction (not fitted on a clamped drum)
    residual_correlation: float = 0.0  # the residual's lag-1 autocorrelation

    def misfit(self) -> str | None:
        """What the residual says the model misses (its lag-1 autocorrelation beyond
        MISFIT_CORRELATION), or None."""
        rho = self.residual_correlation
        if rho <= MISFIT_CORRELATION:
            return None
        return (
            f"the fit's residual is not noise (lag-1 autocorrelation {rho:.2f}, over "
            f"{MISFIT_CORRELATION:g}): something the model does not describe moves the drum "
            "(stiction or friction beyond Coulomb's, force ripple, backlash, a loose "
            "coupling, a load other than the one named); the half-widths are widened for it "
            f"(x{_widening(rho):.2g}) and the estimates may be off by more"
        )

    def actuator_model(self) -> ActuatorModelConfig:
        """The force lag as sim_bus.plant's actuator section (c = [lag])."""
        return ActuatorModelConfig(c=[self.lag])


class Setup(NamedTuple):
    """What the fit knows: the robot file's actuator (starting guess, force limit),
    the load, the cable length (m) and stiffness EA (N)."""

    actuator: ActuatorSpec
    load: Load
    cable_length: float
    stiffness: float
    lag_guess: float = 2e-3
    damping_guess: float = 100.0
    segment: float = 0.25  # s: see segment_residuals


def segment_residuals(
    setup: Setup,
    params: Array,
    data: dict[str, Array],
    fitted: Array | None = None,
    motion: Array | None = None,
) -> Array:
    """Measured minus predicted lengths (m) for parameters `params` (NAMES); the
    predicted lengths also go into `fitted` (one per sample) when given.  `motion` is
    _motion(data), where the caller has it (it does not depend on `params`).

    The record is cut into segments of `segment` seconds; in each, the model starts from
    the initial state that fits best (a linear least-squares problem, solved exactly),
    so a drifting integrator (a free drum, a hanging load) cannot make long horizons
    ill-conditioned, and only m0, k0, the lag, D, the bias and the friction remain for
    scipy."""
    m0, k0, lag, damping, bias, friction = params
    system = _system(setup, m0, k0, lag, damping)
    Ad, Bd, Cd, _, _ = signal.cont2discrete(
        (system.A, system.B, system.C[:1], system.D[:1]), GRID, "zoh"
    )
    t0 = data["command_t"][0]
    per = max(2, round(setup.segment / GRID))
    count = int((data["sample_t"][-1] - t0) / GRID) // per
    grid = t0 + GRID * np.arange(count * per)
    # each command acts from the grid point nearest to when it was sent
    starts = np.round((data["command_t"] - t0) / GRID)
    index = np.searchsorted(starts, np.arange(count * per), side="right") - 1
    u = data["command"][index] - setup.load.hold + bias
    if friction:
        motion = _motion(data) if motion is None else motion
        u = u - friction * np.interp(grid, data["sample_t"], motion)
    u = u.reshape(count, per)
    # every segment's response from rest at once (a transfer function's polynomial
    # loses the precision of poles this close to z = 1)
    forced = np.empty((count, per))
    x = np.zeros((count, Ad.shape[0]))
    c, b, At = Cd[0], Bd[:, 0], Ad.T
    for i in range(per):
        forced[:, i] = x @ c
        x = x @ At + np.outer(u[:, i], b)
    basis = np.empty((per, Ad.shape[0]))
    row = Cd[0].copy()
    for i in range(per):
        basis[i] = row
        row = row @ Ad
    stamps, measured = data["sample_t"], data["length"]
    out = []
    local = np.arange(per) * GRID
    for j in range(count):
        lo, hi = np.searchsorted(stamps, grid[j * per + np.array([0, per - 1])])
        tau = stamps[lo:hi] - grid[j * per]
        y = measured[lo:hi] - np.interp(tau, local, forced[j])
        # the free response, and a constant: the length the load holds the drum at
        # (a rigid-body mode gives one already; a clamped drum has none)
        free = np.column_stack([np.ones(len(tau))] + [np.interp(tau, local, c) for c in basis.T])
        x0, *_ = np.linalg.lstsq(free, y, rcond=None)
        out.append(y - free @ x0)
        if fitted is not None:
            fitted[lo:hi] = measured[lo:hi] - out[-1]
    return np.concatenate(out)


def _motion(data: dict[str, Array]) -> Array:
    """sgn(l') at each sample, softened: tanh of the measured speed (a quadratic
    Savitzky-Golay derivative over SMOOTHING), as cdpr.friction softens it."""
    t, length = data["sample_t"], data["length"]
    step = float(np.median(np.diff(t)))
    window = max(5, 2 * round(SMOOTHING / step / 2) + 1)
    if len(length) <= window:
        return np.zeros(len(length))
    speed = signal.savgol_filter(length, window, 2, deriv=1, delta=step)
    return friction_direction(speed)


def fitted_lengths(setup: Setup, model: Identified, data: dict[str, Array]) -> Array:
    """The model's lengths (m) at the record's samples, each segment from its best
    initial state as in the fit (NaN for samples after the last whole segment)."""
    params = np.array(
        [model.m0, model.k0, model.lag, model.cable_damping or 0.0, model.bias, model.friction]
    )
    if model.cable_damping is None:
        params[3] = setup.damping_guess
    fitted = np.full(len(data["sample_t"]), np.nan)
    segment_residuals(setup, params, data, fitted)
    return fitted


def _system(setup: Setup, m0: float, k0: float, lag: float, damping: float) -> signal.StateSpace:
    spec = setup.actuator.model_copy(update={"m0": m0, "k0": k0})
    config = PlantConfig(
        actuator=ActuatorModelConfig(c=[lag]),
        cable=CableConfig(stiffness=setup.stiffness, damping=damping),
    )
    load = setup.load
    rig = SingleActuatorRig(spec, load.mass, config, setup.cable_length, abs(load.hold))
    return rig.linear_system()


def fit(setup: Setup, data: dict[str, Array]) -> Identified:
    """Least-squares fit of the model to a record (tuning.experiment.Record.arrays())."""
    if len(data["sample_t"]) < 20 or len(data["command_t"]) < 20:
        raise ValueError("too few samples to fit (the experiment ended early)")
    act = setup.actuator
    cabled = setup.load.mass > 0.0
    clamped = math.isinf(setup.load.mass)
    guess = np.array(
        [act.m0, max(act.k0, 0.1), setup.lag_guess, setup.damping_guess, 0.0, FRICTION_GUESS]
    )
    logs = [0, 1, 2, 3]  # fitted as logarithms: positive, and relative steps
    # clamped (module docstring): the bias and the cable's damping stay at the guess, the
    # friction at zero (the drum barely moves)
    free = [0, 1, 2] + ([] if clamped else [4, 5]) + ([3] if cabled and not clamped else [])
    if clamped:
        guess[5] = 0.0

    start = guess.copy()
    start[logs] = np.log(start[logs])
    motion = _motion(data)  # the friction's direction: the data's, whatever the parameters

    def params_of(x: Array) -> Array:
        params = start.copy()
        params[free] = x
        params[logs] = np.exp(params[logs])
        return params

    # within a factor RANGE of the guess either way (the bias is free): a flat direction
    # cannot send a step to exp() overflow
    spread = np.where(np.isin(free, logs), np.log(RANGE), np.inf)
    lower, upper = start[free] - spread, start[free] + spread
    lower[np.equal(free, 5)] = 0.0  # friction opposes motion: never negative
    result = optimize.least_squares(
        lambda x: segment_residuals(setup, params_of(x), data, motion=motion),
        start[free],
        method="trf",
        bounds=(lower, upper),
        x_scale=np.ones(len(free)),
        diff_step=1e-6,
        xtol=1e-10,
        ftol=1e-12,
    )
    params = params_of(result.x)
    measured = data["length"]
    n, p = len(measured), len(free)
    variance = 2.0 * result.cost / max(1, n - p)
    J = result.jac
    try:
        cov = np.linalg.inv(J.T @ J) * variance
        std = np.sqrt(np.abs(np.diag(cov)))
    except np.linalg.LinAlgError:
        std = np.full(p, np.inf)
    rho = _correlation(result.fun)
    # relative half-widths, of the parameters fitted as logarithms
    confidence = {
        NAMES[i]: float(1.96 * _widening(rho) * std[j]) for j, i in enumerate(free) if i in logs
    }
    response = measured - measured.mean()
    return Identified(
        m0=float(params[0]),
        k0=float(params[1]),
        lag=float(params[2]),
        cable_damping=float(params[3]) if 3 in free else None,
        confidence=confidence,
        residual_rms=float(np.sqrt(np.mean(result.fun**2))),
        response_rms=float(np.sqrt(np.mean(response**2))),
        samples=n,
        bias=float(params[4]),
        friction=float(params[5]),
        residual_correlation=rho,
    )


def _correlation(residual: Array) -> float:
    """The lag-1 autocorrelation of `residual` (0 for a constant one)."""
    r = residual - residual.mean()
    energy = float(r @ r)
    return float(r[:-1] @ r[1:]) / energy if energy > 0 else 0.0


def _widening(rho: float) -> float:
    """How much wider a standard error is for a residual of lag-1 autocorrelation rho
    than for white noise: sqrt((1 + rho) / (1 - rho)), the square root of the sample
    count over an AR(1) residual's effective one (rho within [0, 0.99])."""
    rho = min(max(rho, 0.0), 0.99)
    return math.sqrt((1.0 + rho) / (1.0 - rho))
