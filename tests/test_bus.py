"""Real Zenoh on 127.0.0.1 between two OS processes: peer-to-peer and through `safemimic router`."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from shared.bus import TOPICS, Bus, topic_key
from shared.codec import encode
from shared.config import BusConfig
from shared.messages import JointState, Message
from tests.support.bus import BusRecorder
from tests.support.messages import one_of_every_message
from tests.support.processes import free_port

pytestmark = pytest.mark.integration


def content(message: Message) -> dict:
    dumped = message.model_dump(mode="json")
    dumped.pop("seq"), dumped.pop("source")
    return dumped


def exchange_every_message(spawn, test_bus: BusConfig, node_flags: list[str]) -> None:
    with Bus(test_bus, "ping", "test") as bus:
        echoes = BusRecorder(bus, TOPICS, alive=True, robot_id="pong")
        node = spawn("tests/bus_node.py", *node_flags)
        node.wait_json("ready")
        echoes.wait_token("bus_node", True, timeout_s=10)
        publishers = {topic: bus.publisher(topic) for topic in TOPICS}
        sent = one_of_every_message()

        def received() -> set[str]:
            return {topic for topic in TOPICS if echoes.count(topic)}

        deadline = time.monotonic() + 10
        while len(received()) < len(TOPICS) and time.monotonic() < deadline:
            for topic, message in sent.items():  # resend: the node's subscriptions may still propagate
                if topic not in received():
                    publishers[topic].put(message.model_copy())
            time.sleep(0.2)
        assert received() == set(TOPICS), f"echoed back: {sorted(received())}"
        for topic, message in sent.items():
            assert content(echoes.last(topic)) == content(message), topic
            assert type(echoes.last(topic)) is TOPICS[topic]

        # A malformed payload is counted by the receiving process and dropped; the node keeps working.
        bus.put_raw("human/state", b"\x93garbage that is not a message")
        bus.put_raw("robot/command", sent["human/state"].model_dump_json().encode())
        assert node.wait_json("dropped")["counts"].get("human/state", 0) >= 1
        resent = time.monotonic()
        publishers["robot/joint_state"].put(sent["robot/joint_state"].model_copy())
        echoes.wait("robot/joint_state", lambda message: True, timeout_s=5, since=resent)

        # The liveliness token of a killed process disappears within 1 s.
        node.popen.kill()
        killed = time.monotonic()
        gone = echoes.wait_token("bus_node", False, timeout_s=3)
        assert gone - killed <= 1.0, f"token vanished after {gone - killed:.2f}s"


def test_peer_to_peer_exchange(spawn) -> None:
    port = free_port()
    test_bus = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    exchange_every_message(spawn, test_bus, ["--mode", "peer", "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast"])


def test_exchange_through_router(spawn) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = spawn("-m", "safemimic.cli", "router", "--listen", endpoint, "--no-multicast")
    router.wait_for(lambda line: "listening on" in line)
    test_bus = BusConfig(mode="client", connect=[endpoint], multicast_scouting=False)
    exchange_every_message(spawn, test_bus, ["--mode", "client", "--connect", endpoint, "--no-multicast"])


def test_callback_that_raises_does_not_kill_the_session() -> None:
    port = free_port()
    conf = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    seen = threading.Event()
    calls = []

    def flaky(message: Message) -> None:
        calls.append(message.seq)
        if len(calls) == 1:
            raise RuntimeError("boom")
        seen.set()

    with Bus(conf, "solo", "test") as bus:
        bus.subscribe("robot/joint_state", flaky)
        publisher = bus.publisher("robot/joint_state")
        for _ in range(2):
            publisher.put(JointState(stamp=0.0, q=np.zeros(8), dq=np.zeros(8)))
        assert seen.wait(5)
        assert bus.callback_errors["robot/joint_state"] == 1
        assert calls == [0, 1]


def test_unknown_topic_is_a_clear_error() -> None:
    with Bus(BusConfig(mode="peer", multicast_scouting=False), "solo", "test") as bus:
        with pytest.raises(ValueError, match="unknown topic"):
            bus.publisher("robot/nope")
    assert topic_key("g1", "human/state") == "safemimic/g1/human/state"


def test_ingress_caps_name_known_topics_and_positive_rates() -> None:
    solo = BusConfig(mode="peer", multicast_scouting=False)
    with pytest.raises(ValueError, match="unknown topic"):
        Bus(solo, "solo", "viewer", max_hz={"robot/nope": 30.0})
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="positive and finite"):
            Bus(solo, "solo", "viewer", max_hz={"robot/command": bad})


def test_newest_decodes_only_the_newest_valid_sample_of_a_burst() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listen = BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False)
    with Bus(listen, "newest", "reader") as reader, \
            Bus(BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False), "newest", "writer") as writer:
        newest = reader.newest("robot/joint_state")
        assert newest.get() is None
        publisher = writer.publisher("robot/joint_state")
        state = one_of_every_message()["robot/joint_state"]
        deadline = time.monotonic() + 10
        while newest.get() is None:  # the route propagates
            publisher.put(state.model_copy())
            assert time.monotonic() < deadline, "no sample arrived"
            time.sleep(0.05)
        superseded0, count0 = reader.superseded["robot/joint_state"], newest.count
        for i in range(500):  # a burst (blocking puts: none lost): none of it is decoded until read
            writer.put_raw("robot/joint_state", encode(state.model_copy(update={"stamp": 10.0 + i, "seq": i,
                                                                              "source": "burst"})))
        writer.put_raw("robot/joint_state", b"\x93 not a message")  # the newest sample is invalid
        time.sleep(1.0)  # every blocking put is delivered well within this on loopback
        assert newest.count == count0  # nothing read yet
        received = newest.get()
        assert received is not None and received.message.stamp == 10.0 + 499  # the newest valid one
        assert newest.count == count0 + 1
        assert reader.superseded["robot/joint_state"] - superseded0 == 499
        assert reader.dropped["robot/joint_state"] == 1
        assert newest.get() is received  # nothing new: the same holding
