"""``slipd replay RECORDING``: run a recording through the daemon's own decision path, offline.

The recording's samples go through the same ``Detector`` (features -> ensemble -> decision) that
the live loop feeds from the serial reader, as fast as possible, so the alarms printed here are the
alarms the daemon raises on the same frames (a test checks it against the live loop on a pty).

A recording of two sensors (one per finger, ``force`` [N, 2, 9, 3]) replays through the two-sensor
detector whatever the configuration says, as the daemon that recorded it ran: each decision names its
sensor.

Tare, in order of precedence: the offset the daemon used (``meta["tare_offset"]``, written by the
recorder), the configuration's tare (``--config``), the recording's unloaded stretch
(``meta["tare_samples"]``), the model's default stretch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from slipd.detect.build import build_detector
from slipd.detect.decision import Detection
from slipd.detect.detector import SlipDetector, run_recording
from slipd.detect.features import tare_offset
from slipd.recording import Recording

if TYPE_CHECKING:
    from slipd.config import SlipdConfig
    from slipd.detect.ensemble import Ensemble


RATE_TOLERANCE = 0.02
"""How far a recording's sample rate may sit from the model's (timestamps of a real log jitter)."""


def check_rate(rec: Recording, ensemble: Ensemble) -> None:
    """Refuse a recording at another sample rate than the model's (ValueError): the daemon refuses such a sensor rate,
    and the model's windows and median would span another time (a 100 Hz log replayed as 1 kHz misses its slip)."""
    want = float(ensemble.feature_spec.rate_hz)
    stated = rec.meta.get("rate_hz")
    for what, got in (("its timestamps", rec.rate_hz if len(rec) >= 2 else want), ("meta rate_hz", stated)):
        if got is None:
            continue
        if not isinstance(got, (int, float)) or not abs(float(got) - want) <= RATE_TOLERANCE * want:
            raise ValueError(f"sampled at {got!r} Hz by {what}, but the model decides on {want:g} Hz samples")


def detector_for(rec: Recording, ensemble: Ensemble, cfg: SlipdConfig | None = None) -> SlipDetector:
    """The detector the daemon would build for this recording (see the module docstring for the tare)."""
    n = rec.sensors
    if "tare_offset" in rec.meta:
        offset = np.asarray(rec.meta["tare_offset"], np.float32)
        if offset.shape not in ((9, 3), (n, 9, 3)):
            raise ValueError(f"meta tare_offset: shape {list(offset.shape)}, expected [9, 3] or [{n}, 9, 3]")
        return build_detector(cfg, ensemble, offset=offset, sensors=n)
    if cfg is not None:
        return build_detector(cfg, ensemble, sensors=n)
    stretch = rec.meta.get("tare_samples", ensemble.feature_spec.tare_samples)
    integral = isinstance(stretch, (list, tuple)) and all(isinstance(v, (int, np.integer)) for v in stretch)
    if not (integral and len(stretch) == 2):
        raise ValueError(f"meta tare_samples: {stretch!r}, expected [start, stop] sample indices")
    a, b = stretch
    if (a, b) != (0, 0) and not 0 <= a < b <= len(rec):
        raise ValueError(f"meta tare_samples: [{a}, {b}] is not a stretch of its {len(rec)} samples")
    if a == 0:
        return build_detector(None, ensemble, tare_samples=int(b), sensors=n)
    return build_detector(None, ensemble, offset=tare_offset(rec.force, int(a), int(b)), sensors=n)


def replay(rec: Recording, ensemble: Ensemble, cfg: SlipdConfig | None = None) -> list[Detection]:
    """Every decision the daemon makes on ``rec`` (ValueError: a recording at another rate than the model's)."""
    check_rate(rec, ensemble)
    ensemble.reset()
    return run_recording(detector_for(rec, ensemble, cfg), rec.force, rec.t_us, rec.disp)
