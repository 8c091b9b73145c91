"""The holding robot pushed by an external wrench step (tuning/disturbance.py)."""

from __future__ import annotations

import math

import pytest

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from tests.conftest import load_robot
from tuning.disturbance import step_response


@pytest.fixture(scope="module")
def reference8() -> Robot:
    return load_robot("reference8")


def test_a_push_moves_the_platform_its_way_in_proportion_and_the_loop_brings_it_back(
    reference8: Robot,
) -> None:
    spec = ControllerSpec()
    half = step_response(reference8, spec, wrench=(25.0, 0, 0, 0, 0, 0), duration=20.0)
    full = step_response(reference8, spec, wrench=(50.0, 0, 0, 0, 0, 0), duration=20.0)
    assert not half.fault and not full.fault
    assert full.peak_offset_mm[0] > 0.9 * full.peak_mm  # pushed along +x, moved along +x
    assert full.peak_mm / half.peak_mm == pytest.approx(2.0, rel=0.1)  # a linear loop
    assert math.isfinite(full.settle_s) and 0.5 < full.settle_s < 19.5
    assert full.final_mm < 0.02 * full.peak_mm + 0.1  # the integral action took it back


def test_no_push_no_motion(reference8: Robot) -> None:
    still = step_response(reference8, ControllerSpec(), wrench=(0, 0, 0, 0, 0, 0), duration=1.0)
    assert still.peak_mm < 0.05 and still.settle_s == 0.0
