"""`cdprd tune --plot`: the experiment's data, the fit and the gain check in one PNG,
drawn with matplotlib (Agg, no display).

Top: the command (N from the holding force) over the first COMMAND_WINDOW seconds of the
excitation, and the measured length against the fitted model's (and their difference)
over the first WINDOW seconds.  Bottom:
the closed-loop poles of the proposed gains for every mass of the design's sweep (m0 to
1.5x the largest modal mass), the modal-mass range's ends marked, and the step's
settling time and overshoot against the mass.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tuning.experiment import Record
from tuning.gain_design import Design
from tuning.identify import Identified, Setup, fitted_lengths

WINDOW = 2.0  # s of excitation drawn
COMMAND_WINDOW = 0.2  # s of the command drawn (its bits are one period long)


def write_tune_plot(
    path: Path, record: Record, setup: Setup, model: Identified, design: Design
) -> None:
    """The PNG at `path` (its directory must exist; OSError otherwise)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = record.arrays()
    fitted = fitted_lengths(setup, model, data)
    t0 = record.excitation_start if math.isfinite(record.excitation_start) else data["sample_t"][0]
    fig, axes = plt.subplots(2, 2, figsize=(13, 8))
    command, length = axes[0]
    shown = (data["command_t"] >= t0) & (data["command_t"] <= t0 + COMMAND_WINDOW)
    command.step(data["command_t"][shown] - t0, data["command"][shown] - record.hold, where="post")
    command.set_xlabel("time from the excitation's start (s)")
    command.set_ylabel("command - hold (N)")
    command.set_title(f"experiment: PRBS through the drive (hold {record.hold + 0.0:.1f} N)")
    shown = (data["sample_t"] >= t0) & (data["sample_t"] <= t0 + WINDOW)
    ts = data["sample_t"][shown] - t0
    start = data["length"][0]
    length.plot(ts, 1e3 * (data["length"][shown] - start), ".", ms=2, label="measured")
    length.plot(ts, 1e3 * (fitted[shown] - start), "-", lw=1, label="model")
    length.plot(ts, 1e3 * (data["length"][shown] - fitted[shown]), "-", lw=0.8, label="residual")
    length.set_xlabel("time from the excitation's start (s)")
    length.set_ylabel("length - start (mm)")
    length.set_title(
        f"fit: m0 {model.m0:.3g} kg, k0 {model.k0:.3g} N s/m, lag {1e3 * model.lag:.3g} ms; "
        f"residual {1e6 * model.residual_rms:.3g} um RMS"
    )
    length.legend(fontsize="small")
    poles, timing = axes[1]
    masses = np.array([loop.mass for loop in design.sweep])
    if len(masses):
        vmin, vmax = np.log10(masses[[0, -1]])
        for loop in design.sweep:
            p = loop.poles[np.isfinite(loop.poles)]
            shade = np.full(p.size, math.log10(loop.mass))
            pts = poles.scatter(p.real, p.imag, c=shade, s=6, cmap="viridis", vmin=vmin, vmax=vmax)
        fig.colorbar(pts, ax=poles, label="log10 effective mass (kg)")
        settling = [loop.settling_time for loop in design.sweep]
        overshoot = [10.0 * loop.overshoot for loop in design.sweep]
        timing.semilogx(masses, settling, "o-", label="settling (s)")
        timing.semilogx(masses, overshoot, "s--", label="overshoot x10")
    for loop in design.modal:
        poles.plot(loop.poles.real, loop.poles.imag, "r+", ms=8)
        timing.axvline(loop.mass, color="r", lw=0.8)
    timing.axhline(design.settling_target, color="0.5", ls=":", label="settling target")
    poles.set_xscale("symlog", linthresh=1.0)
    poles.set_xlabel("Re s (1/s)")
    poles.set_ylabel("Im s (1/s)")
    g = design.gains
    verdict = "ok" if design.ok else "NOT ok"
    poles.set_title(
        f"closed loop, kp {g.kp:.3g} ki {g.ki:.3g} kd {g.kd:.3g} ({verdict}; +: modal range ends)"
    )
    timing.set_xlabel("effective mass (kg; red: modal-mass range)")
    timing.set_ylabel("s / fraction x10")
    timing.set_title(f"step response, latency {1e3 * design.latency:.3g} ms")
    timing.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
