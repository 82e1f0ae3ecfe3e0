"""The stop and reload signals held back while the devices open (``slipd.daemon.signals.held``), in this process."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator

import pytest

from slipd.daemon import signals


@pytest.fixture
def start_up_handlers() -> Iterator[None]:
    saved = {sig: signal.getsignal(sig) for sig in (*signals.STOP_SIGNALS, signals.RELOAD_SIGNAL)}
    signals.during_start_up()
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)
    signals.reload_pending()


def _from_another_thread(sig: signal.Signals) -> None:
    # Sent while the main thread blocks it: the kernel hands it to a thread that does not (this one, or pytest's),
    # and Python runs the handler on the main thread at its next bytecode, as with the model's threads in slipd.
    worker = threading.Thread(target=os.kill, args=(os.getpid(), sig))
    worker.start()
    worker.join()


def _busy_python(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sum(range(100))


def test_a_stop_inside_the_held_block_is_raised_when_it_ends_not_inside(start_up_handlers: None) -> None:
    reached_the_end = False
    with pytest.raises(signals.StopRequested, match="SIGTERM"), signals.held():
        _from_another_thread(signal.SIGTERM)
        _busy_python(0.2)  # a driver's connect running Python between its calls
        reached_the_end = True
    assert reached_the_end
    assert signal.getsignal(signal.SIGTERM) is signals._StartUp.stop  # the start-up handler is back


def test_a_reload_inside_the_held_block_waits_for_the_loop(start_up_handlers: None) -> None:
    with signals.held():
        _from_another_thread(signal.SIGHUP)
        _busy_python(0.1)
    assert signals.reload_pending() and not signals.reload_pending()


def test_nothing_held_back_means_nothing_raised(start_up_handlers: None) -> None:
    with signals.held():
        _busy_python(0.05)
    with pytest.raises(signals.StopRequested, match="SIGINT"):  # after the block, a stop unwinds at once again
        _from_another_thread(signal.SIGINT)
        _busy_python(0.2)
