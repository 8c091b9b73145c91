"""Two zenoh clients, A and B, against `cdprd run --sim` as its own process (loopback, no
scouting): a lease is its holder's (B can neither release A's observer hold nor take it
over without a lease, so A's lease lapses when A goes quiet, the events naming A), and a
motion is its client's (B's identify_payload and goto are refused while A's trajectory
flies, naming it; a goto saying preempt replaces it and A is told)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

import pytest
import yaml

from daemon.interface.client import CdprClient, RequestError
from tests.loopback import free_port
from tests.processes import CONFIG, PREFIX, ROOT, enabled_sim, wait_status

pytestmark = [pytest.mark.timeout(150), pytest.mark.slow]

QUATERNION = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}


class Stream:
    """A client's events (or states), gathered on zenoh's thread."""

    def __init__(self, subscribe: Callable[[Callable[[dict], None]], object]) -> None:
        self._lock = threading.Lock()
        self._events: list[dict] = []
        self._subscriber = subscribe(self._add)

    def _add(self, event: dict) -> None:
        with self._lock:
            self._events.append(event)

    def named(self, name: str) -> list[dict]:
        with self._lock:
            return [e for e in self._events if e.get("event") == name]

    def last(self) -> dict:
        with self._lock:
            return self._events[-1]

    def close(self) -> None:
        self._subscriber.undeclare()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """A simulated daemon, enabled: its zenoh port."""
    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    config = tmp_path_factory.mktemp("ownership") / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    with enabled_sim(config, port):
        yield port


def _client(port: int, name: str) -> CdprClient:
    return CdprClient(PREFIX, f"tcp/127.0.0.1:{port}", timeout=10.0, name=name)


def _until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"never {what}"
        time.sleep(0.05)


def _refused(call: Callable[[], object]) -> RequestError:
    with pytest.raises(RequestError) as refused:
        call()
    return refused.value


def test_a_lease_is_its_holders(daemon: int) -> None:
    """A holds the observer on a 3 s lease and goes quiet.  B's release, hold without a
    lease and hold on a lease of its own are refused (not_owner, naming A); so the lease
    lapses (within 10 s of A's hold), `lease_lapsed` naming A, and the observer is back
    in.  The hold's event names A; B's refused requests change nothing and make none."""
    with _client(daemon, "A") as a, _client(daemon, "B") as b:
        events = Stream(b.subscribe_events)
        taken = a.observer(True, lease=3.0)
        held_at = time.monotonic()
        assert taken["held"] is True and len(taken["lease_id"]) == 24
        refusals = [
            _refused(lambda: b.observer(False)),
            _refused(lambda: b.observer(True)),
            _refused(lambda: b.observer(True, lease=3.0)),
        ]
        assert b.observer()["held"] is True
        _until(lambda: not b.observer()["held"], 15.0, "let go")
        released_after = time.monotonic() - held_at
        _until(lambda: events.named("lease_lapsed"), 5.0, "told of the lapse")
        lapses, changes = events.named("lease_lapsed"), events.named("hold_changed")
        status = b.status()
        events.close()
    for refusal in refusals:
        assert refusal.code == "not_owner", refusal
        assert "the external wrench observer's hold is on a lease of A's" in refusal.reason
    assert released_after < 10.0, released_after
    assert [(e["what"], e["client"]) for e in lapses] == [("observer", "A")], lapses
    assert [(e["change"], e["client"]) for e in changes] == [("hold", "A")], changes
    assert status["leases"]["observer"] is None and status["state"] == "hold", status


def test_a_motion_is_its_clients_unless_preempted(daemon: int) -> None:
    """A's 4 s trajectory flies: B's identify_payload and goto are refused, naming A's
    trajectory and A; the robot keeps tracking it.  B's goto saying preempt replaces it:
    accepted, A hears `motion_preempted` naming the goto and B, and the robot ends at B's
    target."""
    with _client(daemon, "A") as a, _client(daemon, "B") as b:
        events = Stream(a.subscribe_events)
        states = Stream(b.subscribe_state)
        trajectory = {
            "waypoints": [
                {"t": 0.0, "position": [0.0, 0.0, 1.25], "quaternion": QUATERNION},
                {"t": 4.0, "position": [0.1, 0.0, 1.3], "quaternion": QUATERNION},
            ]
        }
        a.send_trajectory(trajectory, request_id="A-1")
        wait_status(a, "tracking", 5.0)
        identify = _refused(lambda: b.identify_payload())
        goto = _refused(lambda: b.goto([-0.05, 0.0, 1.25]))
        status = b.status()
        replaced = b.goto([-0.05, 0.0, 1.25], preempt=True)
        _until(lambda: events.named("motion_preempted"), 5.0, "told of the preemption")
        (preempted,) = events.named("motion_preempted")
        end = wait_status(a, "hold", 20.0)
        time.sleep(0.5)  # at rest: a state published since
        position = states.last()["pose"]["position"]
        events.close()
        states.close()
    for refusal, what in ((identify, "identify_payload"), (goto, "goto")):
        assert refusal.code == "not_owner", refusal
        assert f"{what} refused: trajectory 'A-1' from A runs" in refusal.reason, refusal
        assert refusal.reply["error"]["running"] == {
            "what": "trajectory", "client": "A", "id": "A-1"
        }  # fmt: skip
    assert status["state"] == "tracking" and status["motion"]["client"] == "A", status
    assert replaced["accepted"] is True
    assert preempted["client"] == "A" and preempted["id"] == "A-1", preempted
    assert preempted["by"] == {"what": "goto", "client": "B"}, preempted
    assert position == pytest.approx([-0.05, 0.0, 1.25], abs=3e-3), position
    assert end["fault"] is None and end["motion"] is None, end
