"""Which signals stop slipd, which reload it, and how each is handled before and while the loop runs.

Every signal whose default action would end the process, and that the process can catch, ends it through the one
clean path SIGTERM takes (the loop stops, the arm's control script is ended, the grip is held, the recorder writes
what it holds) with one log line naming the signal: ``STOP_SIGNALS``. SIGHUP (``systemctl reload``, a closed
terminal) re-reads the configuration instead (``slipd.daemon.reload``). Left as they are: SIGPIPE and SIGXFSZ, which
Python ignores (a write then fails with an error the writer handles: the recorder counts a lost recording), SIGABRT
(systemd's watchdog abort: a wedged loop would never run a handler, and the controller's watchdog halts the arm), and
the signals of a fault in the process itself (SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGSYS, SIGTRAP), after which nothing
the process does can be trusted.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Callable, Iterator
from typing import Any

log = logging.getLogger("slipd.service")

STOP_SIGNALS: tuple[signal.Signals, ...] = (
    signal.SIGTERM, signal.SIGINT, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM,
    signal.SIGVTALRM, signal.SIGPROF, signal.SIGXCPU, signal.SIGPWR, signal.SIGSTKFLT, signal.SIGIO,
)
"""Signals that end slipd the way SIGTERM does (default action: terminate)."""
RELOAD_SIGNAL = signal.SIGHUP


class StopRequested(BaseException):  # a request, like KeyboardInterrupt, not an error
    """A stop signal before the loop runs (start-up: devices being opened, the model warming up): unwinds ``prepare``
    like KeyboardInterrupt, so that whatever was opened is closed again. The loop installs its own handlers;
    ``slipd run`` then exits 0."""


class _StartUp:
    """The handlers while ``prepare`` runs: a stop unwinds it; a reload is remembered and done once the loop runs (the
    config read at start-up may be older than the file)."""

    reload_pending = False

    @staticmethod
    def stop(signum: int, _frame: object) -> None:
        name = signal.Signals(signum).name
        log.warning("%s during start-up: closing what is open and stopping", name)
        raise StopRequested(name)

    @classmethod
    def reload(cls, _signum: int, _frame: object) -> None:
        cls.reload_pending = True


def reload_pending() -> bool:
    """A SIGHUP came during start-up (cleared by the call)."""
    pending, _StartUp.reload_pending = _StartUp.reload_pending, False
    return pending


def _ignored_while_closing(signum: int, _frame: object) -> None:
    log.warning("%s while closing the devices: ignored, the shutdown goes on", signal.Signals(signum).name)


def _on_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _install(handler: Callable[[int, Any], None], signals: tuple[signal.Signals, ...]) -> None:
    if _on_main_thread():  # the main thread alone may install handlers (elsewhere, as in tests: nothing)
        for sig in signals:
            signal.signal(sig, handler)


def during_start_up() -> None:
    """Before ``prepare`` opens anything: a stop unwinds it (``StopRequested``), a reload waits for the loop."""
    _install(_StartUp.stop, STOP_SIGNALS)
    _install(_StartUp.reload, (RELOAD_SIGNAL,))


def while_closing() -> None:
    """The loop's handlers went with it (back to the default: die at once): a second signal must not cut the shutdown
    short, before the arm's control script has ended."""
    _install(_ignored_while_closing, (*STOP_SIGNALS, RELOAD_SIGNAL))


class _Held:
    """The handlers while the devices open: a signal is noted, not acted on (see ``held``)."""

    stop: str | None = None

    @classmethod
    def note(cls, signum: int, _frame: object) -> None:
        if signum == RELOAD_SIGNAL:
            _StartUp.reload_pending = True
        elif cls.stop is None:
            cls.stop = signal.Signals(signum).name


@contextlib.contextmanager
def held() -> Iterator[None]:
    """Hold the stop and reload signals back while the devices open: a stop that lands inside a driver's connect
    (ur_rtde uploading its control script) would unwind before the driver object was kept, and nothing could end
    that script. Delivered when the devices are open and known, so that ``prepare`` closes them.

    Blocking the signals on the main thread is not enough: the kernel hands a process-directed signal to any thread
    that does not block it (the model's and the metrics server's threads were started before), and Python then
    runs the handler on the main thread at its next bytecode, inside the driver's connect. So the handlers only
    note the signal here; the stop is raised once the block ends."""
    main = _on_main_thread()
    blocked = (*STOP_SIGNALS, RELOAD_SIGNAL)
    if not main:  # only the main thread may install handlers or receives Python's signals (tests: nothing to do)
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in blocked}
    _Held.stop = None
    _install(_Held.note, blocked)
    signal.pthread_sigmask(signal.SIG_BLOCK, blocked)  # keeps the drivers' own system calls on this thread whole
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)  # what was pending runs ``_Held.note`` now
        for sig, handler in previous.items():
            if handler is not None:  # None: a handler not set from Python, which cannot be put back from here
                signal.signal(sig, handler)
        name, _Held.stop = _Held.stop, None
    if name is not None:
        log.warning("%s during start-up: closing what is open and stopping", name)
        raise StopRequested(name)


def while_running(loop: Any, stop: Callable[[], None], reload: Callable[[], None]) -> None:
    """On the running asyncio loop: each stop signal logs one line and calls ``stop``; SIGHUP calls ``reload``. Both
    run as loop callbacks, between two blocks of frames: a reload never lands inside a decision."""

    def stopping(sig: signal.Signals) -> None:
        log.info("%s: stopping (arm stopped, grip held, recorder flushed)", sig.name)
        stop()

    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, stopping, sig)
    loop.add_signal_handler(RELOAD_SIGNAL, reload)
