"""One dedicated worker thread per device for blocking vendor calls.

The control loop never blocks: a call to dynamixel-sdk or ur_rtde is handed to the device's own
worker and the loop gets an asyncio future back. One long-lived thread per device (not a thread hop
per sample) keeps the vendor library single-threaded, which neither library is safe without.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


class DeviceWorker:
    """A single-thread executor named after its device."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"slipd-{name}")

    def submit(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> concurrent.futures.Future[T]:
        """Queue ``fn(*args, **kwargs)`` on the device thread; returns a concurrent future."""
        return self._pool.submit(fn, *args, **kwargs)

    async def call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn`` on the device thread and await its result from the event loop."""
        return await asyncio.wrap_future(self.submit(fn, *args, **kwargs))

    def close(self, wait: bool = True) -> None:
        """Stop accepting work; with ``wait`` let queued calls finish."""
        self._pool.shutdown(wait=wait, cancel_futures=not wait)
