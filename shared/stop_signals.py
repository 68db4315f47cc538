"""Stop a service on SIGINT/SIGTERM without taking a lock inside the signal handler.

Python runs a signal handler in the main thread between two bytecodes — possibly while that
thread holds the very lock the handler wants: ``threading.Event.set()`` from a handler deadlocks
when the signal lands inside ``stop.wait()`` (seen: a router stuck forever after a second
SIGTERM). Here the handler only writes a byte to a pipe; a relay thread reads it and sets the
event from a normal thread.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_on_signals(signals: tuple[int, ...] = STOP_SIGNALS) -> Iterator[threading.Event]:
    """An event set once any of ``signals`` arrives (previous handlers restored on exit)."""
    stop = threading.Event()
    read_end, write_end = os.pipe()

    def relay() -> None:
        os.read(read_end, 1)  # a signal's byte, or end of file when the context closes
        stop.set()

    def handler(signum: int, frame: object) -> None:
        try:
            os.write(write_end, b"\0")  # async-signal-safe: no Python lock
        except OSError:  # the pipe is full or closed: a stop is already on its way
            pass

    relay_thread = threading.Thread(target=relay, name="signal-relay", daemon=True)
    relay_thread.start()
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        os.close(write_end)
        relay_thread.join(1.0)
        os.close(read_end)
