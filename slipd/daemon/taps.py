"""Taps: listeners outside the control loop (the ROS 2 publisher, the live view) that see its frames and decisions.

The loop calls ``on_decision`` once per valid decision (after any reaction to it went out) and ``on_block`` once per
block of frames, after the block's decisions, on its own thread; a tap copies what it needs into its own bounded
queue and returns at once, and does its work on its own thread, woken by ``on_block`` (or at its own pace): woken at
each decision, that thread took the interpreter's lock from the loop in the middle of its block. A tap never blocks
and never raises into the loop: a slow consumer loses messages (counted), the loop loses nothing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    import numpy as np

    from slipd.detect.decision import Detection


class Tap(Protocol):
    """What the loop calls on each tap (its own thread; each call returns at once)."""

    def on_block(self, t_us: np.ndarray, force: np.ndarray, disp: np.ndarray) -> None:
        """A block of frames: ``t_us`` [k], ``force`` and ``disp`` [k, S, 9, 3] (the loop's arrays: copy what is
        kept)."""

    def on_decision(self, det: Detection, force: np.ndarray) -> None:
        """A valid decision of sensor ``det.sensor`` and that sensor's frame it was made on (``force`` [9, 3])."""

    def close(self) -> None:
        """Stop the tap's thread and release what it holds (within about a second)."""
