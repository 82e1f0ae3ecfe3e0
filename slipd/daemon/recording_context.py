"""What a recording carries of the daemon beyond frames and decisions: the reactions around it, on the sensor's clock.

``Reaction.records`` keeps each reaction's times on the monotonic clock (decided, sent to the device's thread, done or
failed); the loop's ``stats.alarms`` pairs each alarm's monotonic decision time with its sample's ``t_us``. That pair
puts the reactions on the recording's clock (``slipd.recording_mcap`` writes them on ``/slipd/reactions``).
Called on the loop thread when a recording is cut (both deques are the loop's; no other thread appends to them).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def attach(recorder: Any, daemon: Any) -> None:
    """Have ``recorder``'s recordings carry ``daemon``'s reactions (``meta["reactions"]``)."""
    recorder.extra_meta = lambda t0, t1: {
        "reactions": reactions_between(daemon.reaction.records, daemon.stats.alarms, t0, t1)}


def reactions_between(records: Iterable[Any], alarms: Iterable[tuple[int, int, float, int]], t0_us: int,
                      t1_us: int) -> list[dict[str, Any]]:
    """The reactions decided within [t0_us, t1_us] (sensor clock): one dict per command sent, and per answer (acked,
    or failed with its error). A reaction without an alarm of its own (a fail-safe) is placed by the latest alarm's
    clock offset; without any alarm nothing can be placed, and the list is empty."""
    known = list(alarms)
    if not known:
        return []
    by_time = {t_dec: t_us for _, t_us, t_dec, _ in known}
    _, last_us, last_dec, _ = known[-1]
    out: list[dict[str, Any]] = []
    for rec in list(records):
        base = by_time.get(rec.t_decision)
        if base is None:
            base = round(last_us + (rec.t_decision - last_dec) * 1e6)
        if not t0_us <= base <= t1_us:
            continue

        def at(t: float, base: int = base, t_dec: float = rec.t_decision) -> int:
            return round(base + (t - t_dec) * 1e6)

        for action, t in rec.issued.items():
            out.append({"t_us": at(t), "action": action, "state": "sent", "detail": f"risk {rec.risk:.2f}"})
        for action, t in rec.done.items():
            out.append({"t_us": at(t), "action": action, "state": "acked", "detail": ""})
        for action, err in rec.errors.items():
            t = rec.done.get(action, rec.issued.get(action, rec.t_decision))
            out.append({"t_us": at(t), "action": action, "state": "failed", "detail": str(err)})
    return sorted(out, key=lambda r: r["t_us"])
