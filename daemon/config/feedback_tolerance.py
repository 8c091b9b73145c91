"""The feedback tolerance the trusted-length checks allow (daemon.service.trusted_lengths),
derived from the robot's hardware rather than a fixed millimetre.

Between two samples, and across the cables of one set, measured lengths legitimately
disagree with one rigid motion of the platform by three things the config describes:

- quantisation: each drive reports whole increments of its encoder (q_k m each, from
  drum radius, gear ratio and increments per motor revolution); a change between two
  samples is off by at most q_k per cable, and the consistency check's normalised
  residual of such errors by at most their Euclidean norm, sqrt(sum q_k^2) (the left
  null space's basis is orthonormal);
- noise: the RMS noise of one reported length (drives.encoder_noise, measured at rest):
  NOISE_SIGMAS standard deviations of the difference of two samples, over the cables;
- stretch: the drums measure unstretched cable, and a tension change the plan does not
  know of (safety.unplanned_tension: a hand on the platform, the drives' force error)
  stretches cable k by up to L_max,k / EA_k times it, which the other cables' pose does
  not explain: sqrt(sum (L_max,k / EA_k)^2) times it.

An explicit safety.feedback_tolerance (m) replaces the sum, but not below the
quantisation alone, which every sample may reach.  On reference8 (EA 1e5 N, cables up to
4.2 m, 15 um increments, 8 N unplanned) the sum is 0.99 mm, the 1 mm the checks were
tuned and soaked with; stiffer cables or finer encoders tighten it, coarse ones widen it.

drives.encoder_noise is a figure the builder measured once; the daemon measures it again
whenever it samples the platform at rest (home, pretension, the rest checks:
`measured_noise`, each drive's spread beyond one increment's jitter, which the
quantisation term covers) and says when the tolerance in use is below what that noise
needs (`NoiseWatch`).  It does not widen the tolerance itself: a failing encoder's
noise must not buy itself room.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cdpr import ConfigError, Robot
from drivers.config import DrivesConfig

NOISE_SIGMAS = 6.0  # standard deviations of the noise a difference of two samples may reach
# of the tolerance: a shortfall this small is not said (50 rest samples' second
# differences estimate a noise to ~15 %; the checks' own margin covers it)
SHORTFALL_MARGIN = 0.05
LARGEST = 0.01  # m: a derived tolerance beyond this leaves the checks nothing to judge


@dataclass(frozen=True)
class FeedbackTolerance:
    """The tolerance (m, `total`) and the terms it came from (module docstring);
    `configured`: safety.feedback_tolerance set it instead of the terms' sum."""

    quantisation: float
    noise: float
    stretch: float
    configured: float | None = None
    increments: tuple[float, ...] = ()  # m: each drive's encoder increment in cable length

    @property
    def total(self) -> float:
        if self.configured is not None:
            return self.configured
        return self.quantisation + self.noise + self.stretch

    def describe(self) -> str:
        """One line for check-config."""
        terms = (
            f"quantisation {self.quantisation * 1e3:.3f} + noise {self.noise * 1e3:.3f} + "
            f"stretch {self.stretch * 1e3:.3f} mm"
        )
        if self.configured is None:
            return f"feedback tolerance {self.total * 1e3:.3f} mm ({terms})"
        return f"feedback tolerance {self.total * 1e3:.3f} mm (configured; derived: {terms})"

    def measured_noise(self, lengths: Sequence[Sequence[float]]) -> np.ndarray:
        """Each drive's RMS noise (m) in `lengths` (consecutive cycles x drives) read at
        rest: from the second differences (6 times the variance of white noise; a
        platform still settling, up to the rest checks' speed, drifts out of them),
        beyond what one increment's jitter gives (at most half an increment)."""
        bends = np.diff(np.asarray(lengths, dtype=float), n=2, axis=0)
        variance = np.mean(bends * bends, axis=0) / 6.0
        jitter = 0.5 * np.asarray(self.increments)
        return np.sqrt(np.maximum(variance - jitter * jitter, 0.0))


class NoiseWatch:
    """The encoders' noise measured at rest against the tolerance in use (module
    docstring): `take` a rest sample; an `encoder_noise` event where the tolerance is
    below what the noise needs, by more than SHORTFALL_MARGIN and more than any shortfall
    said before (said once, not at every rest sample)."""

    def __init__(self, tolerance: FeedbackTolerance, nodes: Sequence[int]) -> None:
        self.tolerance = tolerance
        self.nodes = list(nodes)
        self._said = tolerance.total * (1.0 + SHORTFALL_MARGIN)

    def take(self, lengths: Sequence[Sequence[float]]) -> dict[str, Any] | None:
        """The event for `lengths` (consecutive cycles x drives, at rest), or None."""
        t = self.tolerance
        noise = t.measured_noise(lengths)
        needed = t.quantisation + noise_term(noise) + t.stretch
        if needed <= self._said:
            return None
        self._said = needed
        k = int(np.argmax(noise))
        message = (
            f"the encoders are noisier at rest than the feedback tolerance allows: drive {k} "
            f"(node {self.nodes[k]}) {noise[k] * 1e6:.1f} um RMS; the tolerance needs "
            f"{needed * 1e3:.3f} mm, {t.total * 1e3:.3f} mm in use: enter the largest noise "
            f"as drives.encoder_noise ({float(noise[k]):.2g} m), or the daemon may brake on "
            "noise (implausible_feedback)"
        )
        return {"event": "encoder_noise", "message": message, "rms": noise.tolist()}


def noise_term(noise: Sequence[float]) -> float:
    """The tolerance's noise term (m) for each drive's RMS `noise` (m): NOISE_SIGMAS
    standard deviations of the difference of two samples, over the cables."""
    return NOISE_SIGMAS * math.sqrt(2.0 * sum(x * x for x in noise))


def feedback_tolerance(
    robot: Robot,
    drives: DrivesConfig,
    unplanned_tension: float,
    configured: float | None,
) -> FeedbackTolerance:
    """The feedback tolerance of `robot` driven by `drives` (module docstring): the sum
    of its terms, or `configured` (m) where given.  ConfigError where a configured one is
    below the quantisation, or a derived one beyond LARGEST."""
    steps = [abs(s.metres_per_count) for s in drives.scalings_for(robot)]
    if drives.encoder_cpr is not None:  # the encoder behind a position reported in turns
        steps = [q * drives.counts_per_rev / drives.encoder_cpr for q in steps]
    quantisation = math.sqrt(sum(q * q for q in steps))
    noise = noise_term([drives.encoder_noise] * robot.n_cables)
    stretch = unplanned_tension * math.hypot(
        *(length * c for length, c in zip(robot.length_max, robot.compliance, strict=True))
    )
    tolerance = FeedbackTolerance(quantisation, noise, stretch, configured, tuple(steps))
    if configured is not None and configured < quantisation:
        raise ConfigError(
            f"safety.feedback_tolerance: {configured * 1e3:.3f} mm is below what the encoders' "
            f"increments alone reach ({quantisation * 1e3:.3f} mm): every cycle would brake"
        )
    if configured is None and tolerance.total > LARGEST:
        raise ConfigError(
            f"safety.feedback_tolerance: derived as {tolerance.total * 1e3:.1f} mm "
            f"({tolerance.describe()}), beyond {LARGEST * 1e3:g} mm, where the checks judge "
            "nothing: give drives.encoder_cpr (the encoder's increments per motor "
            "revolution, where the drives report turns), or a safety.feedback_tolerance in m"
        )
    return tolerance
