"""sd_notify messages on a real AF_UNIX datagram socket (filesystem and abstract namespace)."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from slipd.daemon.sdnotify import Notifier, notify, watchdog_interval


def _receiver(address: str | bytes) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(address)
    s.settimeout(5)
    return s


@pytest.fixture
def fs_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    s = _receiver(path)
    yield path, s
    s.close()


def test_messages_arrive_in_order(fs_socket):
    path, rx = fs_socket
    with Notifier(path) as n:
        assert n.enabled
        assert n.ready("warming up\nsecond line")
        assert n.status("running: 0 alarms")
        assert n.watchdog()
        assert n.extend_timeout(2.5)
        assert n.stopping()
    got = [rx.recv(4096).decode() for _ in range(5)]
    assert got == [
        "READY=1\nSTATUS=warming up second line",
        "STATUS=running: 0 alarms",
        "WATCHDOG=1",
        "EXTEND_TIMEOUT_USEC=2500000",
        "STOPPING=1",
    ]


def test_abstract_namespace_socket():
    name = f"slipd-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    rx = _receiver(b"\0" + name.encode())
    try:
        with Notifier("@" + name) as n:
            assert n.send("READY=1", STATUS="ok")
        assert rx.recv(4096) == b"READY=1\nSTATUS=ok"
    finally:
        rx.close()


def test_notify_reads_environment(fs_socket, monkeypatch):
    path, rx = fs_socket
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    assert notify("WATCHDOG=1")
    assert rx.recv(4096) == b"WATCHDOG=1"


def test_without_socket_is_a_noop(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled
    assert not n.ready()
    assert not notify("READY=1")


def test_vanished_socket_counts_errors_and_does_not_raise(tmp_path):
    path = str(tmp_path / "gone.sock")
    rx = _receiver(path)
    rx.close()
    os.unlink(path)
    n = Notifier(path)
    assert not n.watchdog()
    assert not n.watchdog()
    assert n.errors == 2
    n.close()


def test_watchdog_interval():
    assert watchdog_interval({"WATCHDOG_USEC": "2000000"}) == 2.0
    assert watchdog_interval({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}) == 2.0
    assert watchdog_interval({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid() + 1)}) is None
    assert watchdog_interval({}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "soon"}) is None
