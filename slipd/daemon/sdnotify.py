"""systemd notifications (``sd_notify``) over ``$NOTIFY_SOCKET``, with a plain socket and no dependency.

With ``Type=notify`` systemd waits for ``READY=1`` before it considers slipd started, shows ``STATUS=``
in ``systemctl status``, restarts slipd when ``WATCHDOG=1`` pings stop for ``WatchdogSec=``, and
learns from ``STOPPING=1`` that a stop is deliberate. Outside systemd (no ``$NOTIFY_SOCKET``) every
call is a cheap no-op returning False.

Sending never blocks (``MSG_DONTWAIT``) and never raises: a full or vanished socket must not stall or
crash the control loop; such failures are counted in ``Notifier.errors``.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping


def _address(path: str) -> str | bytes:
    """``@name`` is a Linux abstract-namespace socket: a leading NUL byte instead of the '@'."""
    if path.startswith("@"):
        return b"\0" + path[1:].encode()
    return path


def watchdog_interval(env: Mapping[str, str] | None = None) -> float | None:
    """The watchdog timeout in seconds from ``$WATCHDOG_USEC``, or None when no watchdog applies.

    ``$WATCHDOG_PID``, when set, must name this process (systemd sets it for the main process only).
    Ping at least every half of the returned interval.
    """
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


class Notifier:
    """One datagram socket to ``$NOTIFY_SOCKET`` (or ``path``), kept open for the process's life."""

    def __init__(self, path: str | None = None) -> None:
        self.path = path if path is not None else os.environ.get("NOTIFY_SOCKET") or None
        self.errors = 0
        self._sock: socket.socket | None = None
        if self.path:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        """True when there is a socket to notify."""
        return self._sock is not None

    def send(self, *fields: str, **named: object) -> bool:
        """Send ``KEY=value`` lines in one datagram: ``send("READY=1")`` or ``send(STATUS="warming up")``."""
        if self._sock is None or self.path is None:
            return False
        lines = list(fields) + [f"{k}={_one_line(v)}" for k, v in named.items()]
        try:
            self._sock.sendto("\n".join(lines).encode(), socket.MSG_DONTWAIT, _address(self.path))
            return True
        except OSError:
            self.errors += 1
            return False

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (and a status line): start-up is complete."""
        return self.send("READY=1", **({"STATUS": status} if status is not None else {}))

    def status(self, text: str) -> bool:
        """``STATUS=text``: shown by ``systemctl status``."""
        return self.send(STATUS=text)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the loop is alive."""
        return self.send("WATCHDOG=1")

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: start-up (tare, warm-up) needs this much longer."""
        return self.send(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutting down on purpose."""
        return self.send("STOPPING=1", **({"STATUS": status} if status is not None else {}))

    def close(self) -> None:
        """Close the socket; later calls are no-ops."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _one_line(value: object) -> str:
    # A newline would start a new assignment in the datagram; keep a status to one field.
    return str(value).replace("\n", " ")


def notify(*fields: str, **named: object) -> bool:
    """One-shot notification to ``$NOTIFY_SOCKET`` (opens and closes a socket; prefer ``Notifier``)."""
    with Notifier() as n:
        return n.send(*fields, **named)
