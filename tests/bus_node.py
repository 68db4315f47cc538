"""A second OS process for the bus tests: echoes every message from robot 'ping' to robot 'pong'.

Prints one JSON line per event on stdout: ``ready``, ``dropped`` (when the drop counter changes).
Holds the liveliness token ``alive/bus_node`` of robot 'ping'.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading

from shared.bus import TOPICS, Bus
from shared.cli_args import add_bus_arguments, config_from_args


def main() -> None:
    parser = argparse.ArgumentParser()
    add_bus_arguments(parser)
    conf = config_from_args(parser.parse_args(), {"robot_id": "ping"})
    stop = threading.Event()
    with Bus(conf.bus, "ping", "bus_node") as bus:
        publishers = {topic: bus.publisher(topic, robot_id="pong") for topic in TOPICS}
        for topic in TOPICS:
            bus.subscribe(topic, publishers[topic].put)
        bus.declare_alive()
        print(json.dumps({"event": "ready"}), flush=True)
        reported = 0
        while not stop.wait(0.05):
            total = sum(bus.dropped.values())
            if total != reported:
                reported = total
                print(json.dumps({"event": "dropped", "counts": dict(bus.dropped)}), flush=True)


if __name__ == "__main__":
    sys.exit(main())
