"""Frame-level fault injection (sim_bus.bus.frame_faults)."""

from __future__ import annotations

import time

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr.description import ConfigError
from sim_bus.bus.frame_faults import (
    FaultyBus,
    FrameFaultInjector,
    error_frame,
    parse_frame_faults,
)
from sim_bus.bus.loopbus import LoopBus


def injector(**section) -> FrameFaultInjector:
    return FrameFaultInjector(parse_frame_faults(section))


def frame(ident: int, i: int = 0, timestamp: float = 0.0) -> can.Message:
    return can.Message(
        timestamp=timestamp,
        arbitration_id=ident,
        is_extended_id=False,
        data=bytes([i & 0xFF, 1, 2, 3, 4, 5, 6, 7]),
    )


def bits_differing(a: bytes, b: bytes) -> int:
    return sum(bin(x ^ y).count("1") for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize(
    ("section", "problem"),
    [
        ({"drop": [{"probability": 0.5, "bogus": 1}]}, "bogus"),
        ({"drop": [{}]}, "probability > 0 or every_nth"),
        ({"corrupt": [{"flip_bits": 2}]}, "probability > 0 or every_nth"),
        ({"drop": [{"probability": 1.5}]}, "probability"),
        ({"drop": [{"every_nth": 0}]}, "every_nth"),
        ({"corrupt": [{"every_nth": 1, "flip_bits": 0}]}, "flip_bits > 0 or change_dlc"),
        ({"delay": [{"delay": 0, "every_nth": 1}]}, "delay"),
        ({"delay": [{"delay": 0.1}]}, "probability > 0 or every_nth"),
        ({"error_bursts": [{"period": 1, "count": 0}]}, "count"),
        ({"drop": [{"every_nth": 2, "match": [{"can_id": 0x20000000}]}]}, "can_id"),
        (
            {
                "drop": [{"name": "x", "every_nth": 2}],
                "delay": [{"name": "x", "delay": 1, "every_nth": 1}],
            },
            "'x' is used twice",
        ),
    ],
)
def test_bad_config_is_named(section: dict, problem: str) -> None:
    with pytest.raises(ConfigError, match=problem):
        parse_frame_faults(section)


def test_drop_every_nth_matching_frame() -> None:
    inj = injector(drop=[{"every_nth": 3}])
    passed = [inj.process(frame(0x181, i), 0.0, "rx") for i in range(9)]
    assert [m is None for m in passed] == [False, False, True] * 3
    assert inj.counts["dropped"] == 3 and inj.counts["passed"] == 6
    assert inj.rule_counts() == {"drop[0]": 3}


def test_drop_a_node_by_id_mask_in_one_direction() -> None:
    """CANopen node 5's frames (cob-id & 0x7F == 5) silenced when the bus user sends."""
    inj = injector(
        drop=[
            {
                "name": "node5",
                "probability": 1.0,
                "direction": "tx",
                "match": [{"can_id": 5, "can_mask": 0x7F}],
            }
        ]
    )
    assert inj.process(frame(0x185), 0.0, "tx") is None
    assert inj.process(frame(0x285), 0.0, "tx") is None
    assert inj.process(frame(0x186), 0.0, "tx") is not None
    assert inj.process(frame(0x185), 0.0, "rx") is not None  # other direction untouched
    assert inj.rule_counts() == {"node5": 2}


def test_passing_frames_are_not_copied_and_error_frames_pass() -> None:
    inj = injector(drop=[{"probability": 1.0, "match": [{"can_id": 0x88, "can_mask": 0xFF}]}])
    msg = frame(0x181)
    assert inj.process(msg, 0.0, "rx") is msg
    err = error_frame(0x88)
    assert inj.process(err, 0.0, "rx") is err  # faults never act on error frames


def test_corrupt_flips_bits_in_a_copy() -> None:
    inj = injector(corrupt=[{"every_nth": 1, "flip_bits": 3}])
    msg = frame(0x181)
    original = bytes(msg.data)
    out = inj.process(msg, 0.0, "rx")
    assert out is not msg and bytes(msg.data) == original
    assert out.dlc == 8 and bits_differing(bytes(out.data), original) == 3
    assert out.arbitration_id == 0x181 and inj.counts["corrupted"] == 1


def test_corrupt_changes_the_dlc_consistently() -> None:
    inj = injector(corrupt=[{"every_nth": 1, "flip_bits": 0, "change_dlc": True}])
    for i in range(30):
        out = inj.process(frame(0x181, i), 0.0, "rx")
        assert out.dlc != 8 and len(out.data) == out.dlc
        assert bytes(out.data) == bytes(frame(0x181, i).data[: out.dlc])


def test_delay_holds_frames_until_due() -> None:
    inj = injector(delay=[{"delay": 0.010, "every_nth": 1, "match": [{"can_id": 0x181}]}])
    assert inj.process(frame(0x181, timestamp=100.0), 5.0, "rx") is None
    assert inj.process(frame(0x182), 5.0, "rx") is not None
    assert inj.held == 1
    assert inj.due(5.009, "rx") == []
    assert inj.due(5.020, "tx") == []  # held for the rx side only
    (late,) = inj.due(5.020, "rx")
    assert late.arbitration_id == 0x181
    assert late.timestamp == pytest.approx(100.020)  # arrives as late as it was held
    assert inj.held == 0 and inj.counts["delayed"] == 1


def test_periodic_error_bursts_and_on_demand_bursts() -> None:
    inj = injector(error_bursts=[{"period": 0.5, "count": 3, "direction": "rx"}])
    assert inj.due(0.0, "rx") == []  # first burst one period after the first call
    assert inj.due(0.4, "rx") == []
    burst = inj.due(0.5, "rx")
    assert len(burst) == 3 and all(m.is_error_frame for m in burst)
    assert burst[0].timestamp == 0.5
    assert inj.due(0.5, "tx") == []
    assert inj.due(0.9, "rx") == []
    assert len(inj.due(3.0, "rx")) == 3  # late: one burst, not five
    inj.error_burst(2, direction="both")
    assert len(inj.due(3.1, "tx")) == 2 and len(inj.due(3.1, "rx")) == 2
    assert inj.counts["error_frames"] == 3 + 3 + 4


def test_rules_switch_on_and_off_at_run_time() -> None:
    inj = injector(drop=[{"name": "loss", "probability": 1.0, "enabled": False}])
    assert not inj.is_enabled("loss")
    assert inj.process(frame(1), 0.0, "rx") is not None
    inj.set_enabled("loss", True)
    assert inj.process(frame(1), 0.0, "rx") is None
    with pytest.raises(KeyError, match="no fault rule named 'los'; rules: loss"):
        inj.set_enabled("los", False)


TRAFFIC = st.lists(
    st.tuples(
        st.integers(0, 0x7FF), st.binary(min_size=0, max_size=8), st.sampled_from(["rx", "tx"])
    ),
    max_size=60,
)


def run_traffic(seed: int, traffic: list) -> list:
    inj = injector(
        seed=seed,
        drop=[{"probability": 0.3}],
        corrupt=[{"probability": 0.4, "flip_bits": 2, "change_dlc": True}],
        delay=[{"probability": 0.2, "delay": 0.002}],
    )
    out = []
    for i, (ident, data, direction) in enumerate(traffic):
        now = i * 0.001
        msg = can.Message(timestamp=now, arbitration_id=ident, data=data, is_extended_id=False)
        m = inj.process(msg, now, direction)
        out.append(None if m is None else (m.arbitration_id, m.dlc, bytes(m.data)))
        out.extend((d.arbitration_id, d.dlc, bytes(d.data)) for d in inj.due(now, direction))
    return [out, dict(inj.counts)]


@given(st.integers(0, 2**32), TRAFFIC)
def test_faults_are_deterministic_given_a_seed(seed: int, traffic: list) -> None:
    assert run_traffic(seed, traffic) == run_traffic(seed, traffic)


def test_different_seeds_give_different_faults() -> None:
    traffic = [(0x100 + i % 7, bytes([i % 256]) * 8, "rx") for i in range(300)]
    assert run_traffic(1, traffic) != run_traffic(2, traffic)


def test_switching_one_rule_leaves_the_others_random_stream_alone() -> None:
    traffic = [frame(0x181, i) for i in range(200)]

    def corrupted(drop_enabled: bool) -> list[int]:
        inj = injector(
            seed=1,
            drop=[{"name": "d", "every_nth": 1, "enabled": drop_enabled, "match": [{"can_id": 7}]}],
            corrupt=[{"name": "c", "probability": 0.5}],
        )
        return [i for i, m in enumerate(traffic) if inj.process(m, 0.0, "rx") is not m]

    assert corrupted(True) == corrupted(False)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_faulty_bus_between_a_simulator_and_the_host() -> None:
    clock = FakeClock()
    config = parse_frame_faults(
        {
            "drop": [{"probability": 1.0, "direction": "tx", "match": [{"can_id": 0x185}]}],
            "delay": [
                {"delay": 0.005, "every_nth": 1, "direction": "rx", "match": [{"can_id": 0x205}]}
            ],
        }
    )
    with (
        LoopBus("faulty") as host,
        FaultyBus(LoopBus("faulty"), config, clock=clock) as sim,
    ):
        sim.send(frame(0x185))  # dropped on the way out
        sim.send(frame(0x186))
        assert [m.arbitration_id for m in host.drain()] == [0x186]

        host.send(frame(0x205))  # delayed on the way in
        host.send(frame(0x206))
        assert sim.fileno() == sim.inner.fileno()
        assert [m.arbitration_id for m in sim.drain()] == [0x206]
        clock.now = 0.004
        assert sim.drain() == []
        clock.now = 0.006
        releasing = time.time()
        [delayed] = sim.drain()
        # received now: stamped at its release, so the drives take it now (sim_bus.runner)
        assert delayed.arbitration_id == 0x205 and delayed.timestamp >= releasing

        sim.injector.error_burst(2, direction="tx")
        sim.tick()
        errors = host.drain()
        assert len(errors) == 2 and all(m.is_error_frame for m in errors)

        host.send(frame(0x206))
        assert sim.recv(1).arbitration_id == 0x206
        inner = sim.inner
    with pytest.raises(can.CanOperationError):
        inner.send(frame(1))  # FaultyBus owns its inner bus
