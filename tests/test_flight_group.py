"""The suite's group of real-time flights, which pytest-xdist runs on one worker, one at
a time (tests/conftest.py): every harness it names exists, and a module is in it by
what it holds."""

from __future__ import annotations

import importlib

import pytest

from tests.conftest import FLIGHT_HARNESSES, flies, qualified_name


@pytest.mark.parametrize("name", sorted(FLIGHT_HARNESSES))
def test_every_flight_harness_exists_under_its_name(name: str) -> None:
    """A renamed or moved harness would leave its flights out of the group unnoticed."""
    module_name, _, attribute = name.rpartition(".")
    try:
        value: object = importlib.import_module(name)
    except ModuleNotFoundError:
        value = getattr(importlib.import_module(module_name), attribute)
    assert qualified_name(value) == name


def test_a_module_is_in_the_group_by_the_harness_it_holds() -> None:
    multibus = importlib.import_module("tests.daemon.test_multibus")  # Stack
    calibrate = importlib.import_module("tests.daemon.test_calibrate_flight")  # processes
    so3 = importlib.import_module("tests.cdpr.test_so3")
    assert flies(multibus) and flies(calibrate) and not flies(so3)
