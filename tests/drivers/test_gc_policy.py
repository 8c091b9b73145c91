"""The daemon's garbage-collection policy: no automatic collection after start-up,
young generations collected between cycles once due, the oldest never."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator

import pytest

from drivers.gc_policy import CollectorPolicy


class Node:
    def __init__(self) -> None:
        self.me = self  # a reference cycle: only the collector frees it


@pytest.fixture
def policy() -> Iterator[CollectorPolicy]:
    policy = CollectorPolicy()
    policy.start()
    try:
        yield policy
    finally:
        policy.close()


def _garbage_cycle() -> weakref.ref:
    return weakref.ref(Node())


def test_start_turns_automatic_collection_off_and_close_back_on() -> None:
    policy = CollectorPolicy()
    assert gc.isenabled()
    policy.start()
    try:
        assert not gc.isenabled()
        assert gc.get_freeze_count() > 0
    finally:
        policy.close()
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_young_garbage_is_collected_between_cycles_once_due(policy: CollectorPolicy) -> None:
    cycle = _garbage_cycle()
    policy.after_cycle()
    assert cycle() is not None, "collected before the young generation was due"
    young, _, _ = gc.get_threshold()
    keep = [[] for _ in range(2 * young)]  # allocations that make a young collection due
    policy.after_cycle()
    assert cycle() is None
    assert policy.stats.young == 1
    assert policy.stats.max_young_us > 0.0
    del keep


def test_the_oldest_generation_is_never_collected(policy: CollectorPolicy) -> None:
    node = Node()
    old = weakref.ref(node)
    gc.collect(1)  # still alive: promoted to generation 2, as a long-lived object is
    del node  # now garbage that only a full collection frees
    for _ in range(50):
        keep = [[] for _ in range(2 * gc.get_threshold()[0])]
        policy.after_cycle()
        del keep
    assert policy.stats.young >= 50
    assert old() is not None, "a full collection ran"


def test_after_close_the_policy_does_nothing() -> None:
    policy = CollectorPolicy()
    policy.start()
    policy.close()
    keep = [[] for _ in range(2 * gc.get_threshold()[0])]
    policy.after_cycle()
    assert policy.stats.young == 0
    del keep
