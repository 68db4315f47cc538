"""The bus's replay/out-of-order rule (:class:`shared.bus.SourceOrder`), directly and through a real
Zenoh session (the fuzz of every subscriber is in ``tests/reliability/test_fuzz.py``)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.bus import RESTART_SILENCE_S, Bus, SourceOrder
from shared.codec import encode
from shared.config import BusConfig
from shared.messages import JointState
from tests.support.bus import await_route
from tests.support.processes import free_port


def joint_state(seq: int, stamp: float, source: str = "executor") -> JointState:
    return JointState(stamp=stamp, seq=seq, source=source, q=np.zeros(8), dq=np.zeros(8))


def test_replays_and_older_messages_are_refused_per_source() -> None:
    order = SourceOrder()
    assert order.accept(joint_state(5, 10.0), received=0.0)
    assert not order.accept(joint_state(5, 10.0), received=0.01)  # a duplicate
    assert not order.accept(joint_state(3, 9.0), received=0.02)  # overtaken by a newer one
    assert order.accept(joint_state(3, 9.0, source="other"), received=0.02)  # sources are independent
    assert order.accept(joint_state(9, 9.5), received=0.03)  # a gap in seq is a loss: accepted
    assert not order.accept(joint_state(8, 11.0 - 1.5), received=0.04)


def test_a_restarted_publisher_is_accepted_again() -> None:
    order = SourceOrder()
    assert order.accept(joint_state(1000, 50.0), received=0.0)
    assert order.accept(joint_state(0, 50.1), received=0.1)  # seq from 0 with a newer stamp: same clock
    assert not order.accept(joint_state(0, 50.1), received=0.2)
    # another host's clock (older stamps): refused while the source is busy, accepted after silence
    assert not order.accept(joint_state(0, 3.0), received=0.3)
    assert order.accept(joint_state(1, 3.1), received=0.1 + RESTART_SILENCE_S + 0.01)
    assert order.accept(joint_state(2, 3.2), received=0.1 + RESTART_SILENCE_S + 0.02)


def test_sources_remembered_are_bounded() -> None:
    order = SourceOrder(max_sources=4)
    for i in range(10):
        assert order.accept(joint_state(7, 1.0, source=f"s{i}"), received=0.0)
    assert order.accept(joint_state(7, 1.0, source="s0"), received=0.0)  # forgotten: taken as new
    assert not order.accept(joint_state(7, 1.0, source="s9"), received=0.0)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.sampled_from(["a", "b"]), st.integers(0, 20), st.integers(0, 20), st.booleans()), max_size=40))
def test_accepted_messages_only_move_forward(events: list[tuple[str, int, int, bool]]) -> None:
    """Whatever arrives, each source's accepted (seq, stamp) never goes back on both at once
    unless the source was silent for longer than the restart silence."""
    order = SourceOrder()
    clock = 0.0
    accepted: dict[str, tuple[int, int, float]] = {}
    for source, seq, stamp, pause in events:
        clock += RESTART_SILENCE_S * 1.5 if pause else 0.01
        taken = order.accept(joint_state(seq, float(stamp), source), received=clock)
        last = accepted.get(source)
        silent = last is not None and clock - last[2] > RESTART_SILENCE_S
        assert taken == (last is None or silent or seq > last[0] or stamp > last[1])
        if taken:
            accepted[source] = (seq, stamp, clock)


@pytest.mark.integration
def test_bus_counts_replays_as_drops_and_keeps_the_newest() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Bus(BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False), "replay", "safety") as bus, \
            Bus(BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False), "replay", "test") as sender:
        latest = bus.latest("robot/joint_state")
        await_route(sender, "robot/joint_state")
        sequence = [(0, 1.0), (1, 1.1), (1, 1.1), (0, 1.0), (2, 1.2), (0, 5.0)]  # dup, old, new, restart
        for seq, stamp in sequence:
            sender.put_raw("robot/joint_state", encode(joint_state(seq, stamp)))
        deadline = time.monotonic() + 5
        while latest.count + bus.dropped["robot/joint_state"] < len(sequence) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert (latest.count, bus.dropped["robot/joint_state"], bus.out_of_order["robot/joint_state"]) == (4, 2, 2)
        assert (latest.get().message.seq, latest.get().message.stamp) == (0, 5.0)
