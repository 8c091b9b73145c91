"""Drive-side length and velocity measurement of the drums.

A drive samples its encoder every plant step.  What it reports at time t is the drum
length of `latency_steps` steps earlier, plus Gaussian noise, quantised to whole
counts (rounded), and the velocity the drive computes from two such samples
`velocity_window_steps` steps apart: (q(t) - q(t - w)) / w.  Each reported sample
draws fresh noise, so the velocity noise has std sqrt(2) noise_std / w.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from sim_bus.plant.config import EncoderConfig


class Encoders:
    """The encoders of n drums, sampled once per plant step of `step` seconds."""

    def __init__(
        self, config: EncoderConfig, n: int, step: float, rng: np.random.Generator
    ) -> None:
        self.n = n
        self.step = step
        self._counts = config.counts_per_metre
        self._noise = config.noise_std
        self._latency = config.latency_steps
        self._window = config.velocity_window_steps
        self._rng = rng
        self._history: deque[tuple[float, ...]] = deque(maxlen=self._latency + self._window + 1)

    def reset(self, lengths: Sequence[float], rates: Sequence[float]) -> None:
        """Fill the history as if the drums had moved at constant `rates` until now."""
        depth = self._history.maxlen or 1
        self._history.clear()
        for age in range(depth - 1, -1, -1):
            dt = age * self.step
            self._history.append(tuple(x - v * dt for x, v in zip(lengths, rates, strict=True)))

    def sample(self, lengths: Sequence[float]) -> None:
        """Record the drum lengths at the end of a plant step."""
        self._history.append(tuple(lengths))

    def read(self, ahead: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(lengths in m, rates in m/s) as the drives report them now, or `ahead` s
        after the last step (less than a step: a drive latching on a SYNC between two
        steps reads its drum then, carried on at the last step's rate, as a real drive
        latches at the SYNC's instant, not at the simulator's step)."""
        history, latency = self._history, self._latency
        now = history[-1 - latency]
        before = history[-1 - latency - self._window]
        if ahead > 0.0:
            # the history holds latency + window + 1 >= latency + 2 steps (reset)
            f = ahead / self.step
            shift = [(a - b) * f for a, b in zip(now, history[-2 - latency], strict=True)]
            now = [a + d for a, d in zip(now, shift, strict=True)]
            before = [a + d for a, d in zip(before, shift, strict=True)]
        if self._noise > 0.0:
            noise = self._rng.normal(0.0, self._noise, (2, self.n)).tolist()
            now = [a + e for a, e in zip(now, noise[0], strict=True)]
            before = [a + e for a, e in zip(before, noise[1], strict=True)]
        counts = self._counts
        if counts is not None:  # whole counts, ties to even as numpy's round
            now = [round(a * counts) / counts for a in now]
            before = [round(a * counts) / counts for a in before]
        dt = self._window * self.step
        return np.array(now), np.array([(a - b) / dt for a, b in zip(now, before, strict=True)])
