"""Ending an emulator's child process: ask it to stop, wait, terminate it if it does not, close the link."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess


def end_child(proc: BaseProcess, conn: Connection | None, ask_to_stop: Callable[[], object],
              ignore: tuple[type[BaseException], ...], join_s: float, terminate_s: float) -> None:
    """Ask a live child to stop (errors in ``ignore`` are expected from a child already going), wait up to
    ``join_s``, terminate it if it is still alive and wait ``terminate_s`` more, then close ``conn``."""
    if conn is not None and proc.is_alive():
        with contextlib.suppress(*ignore):
            ask_to_stop()
    proc.join(timeout=join_s)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout=terminate_s)
    if conn is not None:
        conn.close()
