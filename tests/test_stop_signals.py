"""SIGINT/SIGTERM set the stop event through a relay thread; nothing deadlocks however they land."""

from __future__ import annotations

import os
import signal

from shared.stop_signals import stop_on_signals


def test_signals_set_the_event_even_mid_wait_and_handlers_are_restored() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with stop_on_signals() as stop:
        assert not stop.is_set()
        for _ in range(50):  # many signals while the main thread sits in stop.wait(): no deadlock
            os.kill(os.getpid(), signal.SIGTERM)
            stop.wait(0.001)
        assert stop.wait(2.0)
    assert signal.getsignal(signal.SIGTERM) is before
