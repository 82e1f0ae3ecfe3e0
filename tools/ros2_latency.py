"""Latency of the ROS 2 alarm on loopback: the loop's ``on_decision`` -> a zenoh subscriber's callback with the
decoded ``std_msgs/Bool``.

    python tools/ros2_latency.py [--alarms 200] [--period-ms 10]

A subscriber session listens on 127.0.0.1; ``slipd.daemon.ros2.Ros2Publisher`` (its thread, its queue, rosbags'
CDR, rmw_zenoh's key expressions) connects to it. Each round hands the publisher one decision that raises the alarm
and one that clears it, ``--period-ms`` apart, each followed by the end of its block (``on_block``), as the loop
does; the time from the raising ``on_decision`` call to the callback that decodes ``data: true`` is one sample.
Prints the median, p99 and maximum.
"""

from __future__ import annotations

import argparse
import socket
import threading
import time

import numpy as np

from slipd.config import Ros2Config
from slipd.daemon.ros2 import TYPES, Messages, Ros2Publisher, session_config
from slipd.detect.decision import Detection


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--alarms", type=int, default=200)
    ap.add_argument("--period-ms", type=float, default=10.0)
    args = ap.parse_args()
    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    sub_session = zenoh.open(session_config("peer", [], [f"tcp/127.0.0.1:{port}"]))
    msgs = Messages()
    rx: list[float] = []
    got = threading.Event()

    def on_alarm(sample) -> None:  # type: ignore[no-untyped-def]
        t = time.perf_counter()
        if msgs.decode(sample.payload.to_bytes(), TYPES["alarm"]).data:
            rx.append(t)
            got.set()

    pub = Ros2Publisher(Ros2Config(enabled=True, connect=[f"tcp/127.0.0.1:{port}"])).start()
    sub = sub_session.declare_subscriber(pub.keys["/slip/alarm"], on_alarm)
    time.sleep(1.0)  # the sessions connect
    force = np.zeros((9, 3), np.float32)
    block, block_t = np.zeros((1, 1, 9, 3), np.float32), np.zeros(1, np.int64)
    lat = []
    for k in range(args.alarms):
        got.clear()
        n = len(rx)
        t0 = time.perf_counter()
        pub.on_decision(Detection(2 * k, 2000 * k, 0.9, 1.0, True, True), force)
        pub.on_block(block_t, block, block)  # the loop's block ends: the ros2 thread wakes
        if got.wait(1.0) and len(rx) > n:
            lat.append(rx[n] - t0)
        time.sleep(args.period_ms / 2e3)
        pub.on_decision(Detection(2 * k + 1, 2000 * k + 1000, 0.1, 0.0, False, False), force)
        pub.on_block(block_t, block, block)
        time.sleep(args.period_ms / 2e3)
    pub.close()
    sub.undeclare()
    sub_session.close()
    ms = np.array(lat) * 1e3
    print(f"alarms sent {args.alarms}, received {len(lat)}, dropped by the queue {pub.dropped}")
    if len(ms):
        print(f"on_decision -> subscriber decoded the alarm: median {np.median(ms):.3f} ms, "
              f"p99 {np.percentile(ms, 99):.3f} ms, max {ms.max():.3f} ms")


if __name__ == "__main__":
    main()
