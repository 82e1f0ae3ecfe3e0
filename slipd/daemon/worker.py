"""One dedicated worker thread per device for blocking vendor calls.

The control loop never blocks: a call to dynamixel-sdk or ur_rtde is handed to the device's own
worker and the loop gets an asyncio future back. One long-lived thread per device (not a thread hop
per sample) keeps the vendor library single-threaded, which neither library is safe without.

The thread is a daemon thread with a bounded ``close``: after a dropped link a vendor call can sit in its
own reconnect timeouts for minutes, and a daemon asked to stop must still exit (the controller's watchdog
halts the arm when slipd is gone) instead of waiting on that call at interpreter exit.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import queue
import threading
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

_Item = tuple["concurrent.futures.Future[Any]", Callable[..., Any], tuple[Any, ...], dict[str, Any]]


class DeviceWorker:
    """A single thread named after its device that runs the calls handed to it, in order."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._queue: queue.SimpleQueue[_Item | None] = queue.SimpleQueue()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"slipd-{name}", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> concurrent.futures.Future[T]:
        """Queue ``fn(*args, **kwargs)`` on the device thread; returns a concurrent future."""
        if self._closed:
            raise RuntimeError(f"device worker {self.name!r} is closed")
        fut: concurrent.futures.Future[T] = concurrent.futures.Future()
        self._queue.put((fut, fn, args, kwargs))
        return fut

    async def call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn`` on the device thread and await its result from the event loop."""
        return await asyncio.wrap_future(self.submit(fn, *args, **kwargs))

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            self._run_one(item)
            # A finished call's arguments (a recording's frames: megabytes for a long episode) must not stay
            # alive while the thread waits for the next one.
            del item

    @staticmethod
    def _run_one(item: _Item) -> None:
        fut, fn, args, kwargs = item
        if not fut.set_running_or_notify_cancel():
            return
        try:
            result = fn(*args, **kwargs)
        except BaseException as exc:  # handed to whoever awaits the future
            fut.set_exception(exc)
        else:
            fut.set_result(result)

    def close(self, wait: bool = True, timeout: float | None = None) -> bool:
        """Stop accepting work. ``wait``: let queued calls finish (for at most ``timeout`` seconds, None:
        however long); else cancel those not started. True when the thread has ended."""
        if not self._closed:
            self._closed = True
            if not wait:
                while True:
                    try:
                        item = self._queue.get_nowait()
                    except queue.Empty:
                        break
                    if item is not None:
                        item[0].cancel()
            self._queue.put(None)
        if wait:
            self._thread.join(timeout)
        return not self._thread.is_alive()
