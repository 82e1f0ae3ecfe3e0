"""The feature pipeline: one implementation for training, evaluation, replay and the daemon.

Stages, in order, per sample:
    1. sanitise   a non-finite value (NaN, +-Inf) is replaced by the last finite value of that
                  channel (0 before any finite value was seen, i.e. "no load") and counted;
    2. tare       the unloaded offset is subtracted (``offset`` [9, 3], from ``tare_offset`` or 0 when
                  the sensor's own bias command zeroed it);
    3. clip       tared forces are clipped to twice the sensor's range, so an absurd value (1e6 N)
                  becomes a short, bounded spike that the median filter removes;
    4. select     the manifest's pillars and channels, pillar-major: [P_a fx, P_a fy, P_b fx, ...]
                  (a spec with a derived channel selects all three axes of its pillars here);
    5. median     causal median of the last ``median`` samples. At the start of a stream the history
                  is filled with copies of the first sample (edge padding), so every output is the
                  median of exactly ``median`` values: defined, exact (an element, no averaging) and
                  identical between streaming and batch;
    5b. derive    only for specs with a derived channel (``DERIVED``): per filtered sample, the
                  derived channels are computed from that pillar's filtered fx, fy, fz and the
                  spec's channels are put in order (``FeatureSpec.derive``, the one function both
                  paths call); a channel that compares a sample with an earlier one (``WINDOWED``)
                  reads only the samples of its own window, so both paths derive window by window;
    6. window     ``window`` consecutive filtered samples flattened time-major ([T, C] -> [T*C]).
                  Windows end every ``stride`` samples (``stride == window``: the method's
                  non-overlapping windows); the first ends at sample ``window - 1``.

``FeatureStream`` (sample by sample, constant memory) and ``batch_windows`` (whole recordings,
vectorised) compute the same floating-point operations on the same values and give bit-identical
windows; ``tests/detect/test_features.py`` proves it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from slipd.geometry import CONTACT_THRESHOLD_N, FT_RANGE_N, FZ_RANGE_N, N_PILLARS, OUTER

CHANNEL_INDEX = {"fx": 0, "fy": 1, "fz": 2}
DERIVED = ("util", "lutil", "ux", "uy", "gft", "gfz", "rspeed")
"""Derived channels, computed from a pillar's filtered forces after the median (stage 5b):

util  friction utilisation |Ft| / max(Fz, 0.5 N): the share of the friction cone a pillar uses, up to the
      (unknown) friction coefficient. A pillar that slides carries mu_k * Fz, so while the whole contact
      slides every in-contact pillar shows the same value, whereas a sticking contact shares its load by
      deflection, not by normal force. The ratio is independent of grip force and object weight, which is
      what lets one model read both a 30 N hexapod press and a light 8 N grasp. The floor is the SDK's
      contact threshold: a pillar off the surface reads noise / 0.5 N, near 0.
lutil ln(max(util, 0.01)): the same on a log scale, where "every pillar uses the same share of its friction
      cone" is a difference of zero between pillars whatever the friction coefficient (0.1 or 0.9), a
      comparison a first linear layer makes directly. The floor keeps noise on unloaded pillars at -4.6.
ux, uy fx / max(Fz, 0.5 N) and fy / max(Fz, 0.5 N): the utilisation as a vector (util is its length), which
      keeps the direction each pillar is loaded in (a rotation loads pillars in different directions).
gft   |Ft| / max(sum of Fz, 0.5 N): a pillar's tangential force over the whole grasp's normal load (the spec's
      pillars), so a 2 N grasp reads like a 20 N one; unlike util it stays defined on pillars that barely touch.
gfz   Fz / max(sum of Fz, 0.5 N): each pillar's share of the grasp's normal load (how the contact is spread:
      a flat face over nine pillars, a curved one over two or three), whatever the grip.
rspeed a pillar's tangential deflection speed over that of the fastest pillar: |Ft(t) - Ft(t - 10 ms)| (the
      force vector's change, which is k_t times the tip's deflection) over the largest such change among the
      spec's pillars, at least ``RSPEED_FLOOR_N``. What the reference-pillar heuristic reads: while a tip sticks
      it deflects with the object, once it slides its deflection stops growing, so a slipping pillar falls
      behind the ones that still stick, at any grip, friction or load rate. Within the first 10 ms of a window
      the lag reaches back to the window's first sample only (``WINDOWED``).
"""
WINDOWED = ("rspeed",)
"""Derived channels that compare a sample with an earlier one; they read the samples of their own window only."""
RSPEED_LAG = 10
"""Samples over which ``rspeed`` measures a deflection speed (10 ms: the heuristics' lag)."""
RSPEED_FLOOR_N = np.float32(0.035)
"""Smallest fastest-pillar change (N per 10 ms) that ``rspeed`` divides by: 1 mm/s of a v2 tip (3.5 N/mm), the
reference-pillar heuristic's smallest reference speed; below it (a still grasp) every pillar reads its own change
over this floor, near 0."""
ALL_CHANNELS = (*CHANNEL_INDEX, *DERIVED)
UTIL_FLOOR_N = CONTACT_THRESHOLD_N
_UTIL_FLOOR_F32 = np.float32(UTIL_FLOOR_N)
LUTIL_FLOOR = np.float32(0.01)
CLIP_N = np.array([2 * FT_RANGE_N, 2 * FT_RANGE_N, 2 * FZ_RANGE_N], dtype=np.float32)
"""Bound on tared forces per axis (twice the sensor's range)."""


def channel_bound(channel: str) -> float:
    """Largest magnitude ``channel`` can take in a window (clipped forces; util from clipped forces)."""
    if channel == "util":
        return float(np.hypot(CLIP_N[0], CLIP_N[1]) / UTIL_FLOOR_N)
    if channel in ("ux", "uy"):
        return float(CLIP_N[0] / UTIL_FLOOR_N)
    if channel == "lutil":
        return float(max(np.log(channel_bound("util")), -np.log(LUTIL_FLOOR)))
    if channel == "gft":
        return channel_bound("util")
    if channel == "gfz":
        return float(CLIP_N[2] / UTIL_FLOOR_N)
    if channel == "rspeed":
        return 1.0
    return float(CLIP_N[CHANNEL_INDEX[channel]])
TARE_GLITCH_FLOOR_N = 0.05
"""Smallest deviation from the median that ``tare_offset`` may treat as a glitch (five noise sigmas)."""


@dataclass(frozen=True)
class FeatureSpec:
    """Which pillars and channels feed the model, and how samples become windows.

    The model manifest stores exactly these fields; the daemon refuses a model whose spec differs
    from what its feature code would produce.
    """

    pillars: tuple[int, ...] = OUTER
    channels: tuple[str, ...] = ("fx", "fy")
    window: int = 40
    median: int = 21
    rate_hz: int = 1000
    stride: int = 0
    """Samples between decisions; 0 means ``window`` (non-overlapping windows)."""
    tare_samples: tuple[int, int] = (0, 100)
    """Default unloaded stretch [start, stop) of a recording used for the offset."""
    _cols: tuple[int, ...] = field(default=(), repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.pillars or any(not 0 <= p < N_PILLARS for p in self.pillars):
            raise ValueError(f"pillars must be SDK indices 0..8, got {self.pillars}")
        if len(set(self.pillars)) != len(self.pillars):
            raise ValueError(f"pillars repeat: {self.pillars}")
        unknown = [c for c in self.channels if c not in ALL_CHANNELS]
        if unknown or not self.channels or len(set(self.channels)) != len(self.channels):
            raise ValueError(f"channels must be distinct, among {', '.join(ALL_CHANNELS)}, got {self.channels}")
        if self.window < 1 or self.median < 1 or self.median % 2 == 0:
            raise ValueError(f"window >= 1 and an odd median width are required (got {self.window}, {self.median})")
        if not 0 <= self.stride <= self.window:
            raise ValueError(f"stride must be in 0..window, got {self.stride}")
        if self.derived:
            cols = tuple(p * 3 + a for p in self.pillars for a in range(3))
        else:
            cols = tuple(p * 3 + CHANNEL_INDEX[c] for p in self.pillars for c in self.channels)
        object.__setattr__(self, "_cols", cols)

    @cached_property
    def derived(self) -> bool:
        """True when a channel is computed after the median (stage 5b) rather than selected."""
        return any(c in DERIVED for c in self.channels)

    @cached_property
    def windowed(self) -> bool:
        """True when a channel reads earlier samples of its window (``WINDOWED``): derived window by window."""
        return any(c in WINDOWED for c in self.channels)

    @cached_property
    def n_base(self) -> int:
        """Columns selected in stage 4 and median-filtered (equals ``n_channels`` without derived channels)."""
        return len(self._cols)

    def derive(self, filtered: np.ndarray) -> np.ndarray:
        """Stage 5b: [T, n_base] filtered samples -> [T, n_channels]; the identity without derived channels.

        Elementwise float32 arithmetic per sample, so any split of a recording into pieces gives the same
        values bit for bit (the streaming and batch paths both call this). A ``windowed`` spec takes whole
        windows, ``T`` a multiple of ``window`` (one window, or several stacked).
        """
        if not self.derived:
            return filtered
        f = filtered.reshape(len(filtered), len(self.pillars), 3)
        fz = np.maximum(f[:, :, 2], _UTIL_FLOOR_F32)
        if self.channels == ("util",):
            # The shipped model's layout, once per decision on the hot path: no stack of one part (same values).
            out: np.ndarray = np.hypot(f[:, :, 0], f[:, :, 1])
            np.divide(out, fz, out=out)
            return out.reshape(len(filtered), self.n_channels)
        parts = []
        util = np.hypot(f[:, :, 0], f[:, :, 1]) / fz if {"util", "lutil"} & set(self.channels) else fz
        grasp = np.maximum(f[:, :, 2].sum(axis=1, keepdims=True), np.float32(UTIL_FLOOR_N))
        for c in self.channels:
            if c == "ux":
                parts.append(f[:, :, 0] / fz)
            elif c == "uy":
                parts.append(f[:, :, 1] / fz)
            elif c == "util":
                parts.append(util)
            elif c == "lutil":
                parts.append(np.log(np.maximum(util, LUTIL_FLOOR)))
            elif c == "gft":
                parts.append(np.hypot(f[:, :, 0], f[:, :, 1]) / grasp)
            elif c == "gfz":
                parts.append(f[:, :, 2] / grasp)
            elif c == "rspeed":
                parts.append(self._rspeed(f))
            else:
                parts.append(f[:, :, CHANNEL_INDEX[c]])
        return np.stack(parts, axis=-1).astype(np.float32, copy=False).reshape(len(filtered), self.n_channels)

    def _rspeed(self, f: np.ndarray) -> np.ndarray:
        """[T, P] ``rspeed`` of [T, P, 3] filtered forces, T a multiple of the window (each window on its own)."""
        w = f[:, :, :2].reshape(-1, self.window, len(self.pillars), 2)
        lag = min(RSPEED_LAG, self.window - 1)
        before = np.empty_like(w)
        before[:, lag:] = w[:, :-lag] if lag else w
        before[:, :lag] = w[:, :1]
        d = w - before
        speed = np.hypot(d[..., 0], d[..., 1])
        fastest = np.maximum(speed.max(axis=-1, keepdims=True), RSPEED_FLOOR_N)
        out: np.ndarray = (speed / fastest).reshape(len(f), len(self.pillars))
        return out

    @cached_property
    def n_channels(self) -> int:
        """Features per sample (C)."""
        return len(self.pillars) * len(self.channels)

    @cached_property
    def input_size(self) -> int:
        """Length of one flattened window (T * C)."""
        return self.window * self.n_channels

    @cached_property
    def step(self) -> int:
        """Samples between two consecutive windows."""
        return self.stride or self.window

    @property
    def columns(self) -> tuple[int, ...]:
        """Indices into a flattened [9*3] sample, in feature order."""
        return self._cols

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form for the manifest."""
        d = asdict(self)
        d.pop("_cols", None)
        d["pillars"] = list(self.pillars)
        d["channels"] = list(self.channels)
        d["tare_samples"] = list(self.tare_samples)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FeatureSpec:
        """Inverse of ``to_dict``; unknown keys raise ``TypeError``."""
        d = dict(d)
        for key in ("pillars", "channels", "tare_samples"):
            if key in d:
                d[key] = tuple(d[key])
        return cls(**d)

    def with_(self, **changes: Any) -> FeatureSpec:
        """A copy with some fields changed."""
        d = self.to_dict()
        d.update(changes)
        return FeatureSpec.from_dict(d)


def tare_offset(force: np.ndarray, start: int = 0, stop: int = 100) -> np.ndarray:
    """[9, 3] float32 mean of ``force[start:stop]`` (an unloaded stretch), ignoring non-finite values and
    glitches: samples farther than ``max(6 sigma, 0.05 N)`` from the channel's median (sigma estimated from
    the median absolute deviation) are left out, so one 1e6 N spike cannot shift the offset, and with it
    every later feature, by 1e6 / n N. On clean sensor noise nothing is left out (the plain mean).

    Accumulates in float64 so long stretches do not bias the offset.
    """
    seg = np.asarray(force[start:stop], dtype=np.float64)
    if seg.shape[0] == 0:
        raise ValueError(f"empty tare stretch [{start}, {stop}) of a {len(force)}-sample recording")
    finite = np.isfinite(seg)
    vals = np.where(finite, seg, np.nan)
    vals[:, ~finite.any(axis=0)] = 0.0  # never finite: a dummy 0 (its offset is 0 below), so nanmedian won't warn
    med = np.nanmedian(vals, axis=0)
    dev = np.abs(vals - med)
    sigma = 1.4826 * np.nanmedian(dev, axis=0)
    finite &= dev <= np.maximum(6.0 * sigma, TARE_GLITCH_FLOOR_N)  # NaN compares False: stays excluded
    count = finite.sum(axis=0)
    total = np.where(finite, seg, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0).astype(np.float32)


def stretch_offset(force: np.ndarray, stretch: Sequence[int]) -> np.ndarray:
    """The offset of a recording from its unloaded ``stretch`` [start, stop) (``meta["tare_samples"]``).

    ``[0, 0]`` names no stretch: the sensor zeroed itself (its bias command) before the recording, as for
    a recording that starts mid-grasp, so the offset is 0.
    """
    start, stop = (int(v) for v in stretch)
    if start == stop == 0:
        return np.zeros((N_PILLARS, 3), np.float32)
    return tare_offset(force, start, stop)


def _hold_last_finite(x: np.ndarray) -> tuple[np.ndarray, int]:
    """Forward-fill non-finite entries along axis 0 (0 before the first finite value)."""
    bad = ~np.isfinite(x)
    n_bad = int(bad.sum())
    if not n_bad:
        return x, 0
    idx = np.where(bad, 0, np.arange(len(x))[:, None])
    np.maximum.accumulate(idx, axis=0, out=idx)
    filled = x[idx, np.arange(x.shape[1])[None, :]]
    # Rows before any finite value of the channel: np.maximum.accumulate points at row 0, which is bad.
    filled = np.where(np.isfinite(filled), filled, np.float32(0.0))
    return filled.astype(np.float32, copy=False), n_bad


def prepare_samples(force: np.ndarray, spec: FeatureSpec, offset: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Stages 1-4 on a whole recording: [N, 9, 3] raw forces -> [N, n_base] float32, and the non-finite count."""
    flat = np.asarray(force, dtype=np.float32).reshape(len(force), N_PILLARS * 3)
    flat, n_bad = _hold_last_finite(flat)
    off = np.zeros(N_PILLARS * 3, np.float32) if offset is None else np.asarray(offset, np.float32).reshape(-1)
    clip = np.tile(CLIP_N, N_PILLARS)
    tared = np.clip(flat - off, -clip, clip)
    return np.ascontiguousarray(tared[:, spec.columns]), n_bad


def sliding_median(hist: np.ndarray, width: int) -> np.ndarray:
    """Median of every run of ``width`` consecutive rows of ``hist`` [M, C] -> [M - width + 1, C] float32.

    An odd-width median is one of its inputs, so any exact method gives the same bits. Widths 3 and 5
    (the shipped model's) use min/max selection networks over shifted views: about a hundred times faster
    than ``np.median`` over a sliding view, which dominated the cost of a training epoch; other widths
    use ``np.median``.
    """
    n = len(hist) - width + 1
    if width == 3:
        a, b, c = hist[0:n], hist[1 : n + 1], hist[2 : n + 2]
        return _median3(a, b, c).astype(np.float32, copy=False)
    if width == 5:
        # median5 = median3(e, max(min(a, b), min(c, d)), min(max(a, b), max(c, d))) of the rows a..e of each run: the
        # larger of the two pair minima and the smaller of the two pair maxima bracket the median of a..d's middle
        # pair. A pair (a, b) is two consecutive rows, and so is (c, d), two rows further: one minimum and one maximum
        # of every two consecutive rows serve both pairs. Arrays written in place (this runs once per decision on the
        # daemon's hot path, where the number of numpy calls sets the cost).
        m = n + 2
        pair_min = np.minimum(hist[0:m], hist[1 : m + 1])
        pair_max = np.maximum(hist[0:m], hist[1 : m + 1])
        lo = np.maximum(pair_min[0:n], pair_min[2 : n + 2])
        hi = np.minimum(pair_max[0:n], pair_max[2 : n + 2])
        e = hist[4 : n + 4]
        # median3(e, lo, hi) = max(min(e, lo), min(max(e, lo), hi)), as ``_median3``
        t = np.maximum(e, lo, out=pair_max[0:n])
        np.minimum(t, hi, out=t)
        np.minimum(e, lo, out=lo)
        np.maximum(lo, t, out=lo)
        med: np.ndarray = lo.astype(np.float32, copy=False)
        return med
    out: np.ndarray = np.median(sliding_window_view(hist, width, axis=0), axis=-1).astype(np.float32)
    return out


def _median3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
    return out


def causal_median(x: np.ndarray, width: int) -> np.ndarray:
    """Causal median of the last ``width`` samples, edge-padded at the start. [N, C] -> [N, C]."""
    if width == 1 or len(x) == 0:
        return x.copy()
    padded = np.concatenate([np.repeat(x[:1], width - 1, axis=0), x], axis=0)
    return sliding_median(padded, width)


def window_ends(n_samples: int, spec: FeatureSpec) -> np.ndarray:
    """Indices of the last sample of each window a stream of ``n_samples`` produces."""
    return np.arange(spec.window - 1, n_samples, spec.step, dtype=np.int64)


def batch_windows(
    force: np.ndarray, spec: FeatureSpec, offset: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The whole pipeline on a recording: ([K, T*C] float32 windows, [K] index of each window's last sample)."""
    x, _ = prepare_samples(force, spec, offset)
    filtered = causal_median(x, spec.median)
    if spec.windowed:
        # A channel that reads earlier samples of its window: cut the filtered base windows, then derive each.
        base, ends = _cut_windows(filtered, spec)
        return spec.derive(base.reshape(-1, spec.n_base)).reshape(len(ends), spec.input_size), ends
    return _cut_windows(spec.derive(filtered), spec)


def _cut_windows(rows: np.ndarray, spec: FeatureSpec) -> tuple[np.ndarray, np.ndarray]:
    """[N, C] filtered (or derived) samples -> ([K, T * C] windows, time-major, [K] index of each window's last)."""
    ends = window_ends(len(rows), spec)
    width = spec.window * rows.shape[1]
    if len(ends) == 0:
        return np.zeros((0, width), np.float32), ends
    if spec.step == spec.window:
        # Non-overlapping windows are consecutive blocks of the time-major samples: a reshape.
        return np.ascontiguousarray(rows[: len(ends) * spec.window]).reshape(len(ends), width), ends
    starts = ends - spec.window + 1
    wins = sliding_window_view(rows, spec.window, axis=0)[starts]  # [K, C, T]
    return np.ascontiguousarray(wins.transpose(0, 2, 1)).reshape(len(ends), width), ends


def window_labels(label: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Label of each window = label of its last sample (the method's rule)."""
    out: np.ndarray = np.asarray(label)[ends]
    return out


class FeatureStream:
    """Streaming form of ``batch_windows``: push one raw sample at a time, get a window when one completes.

    Memory is constant: a history of ``median - 1 + window`` prepared samples. The median of a whole
    window is computed once, when the window completes, with the same vectorised call as the batch
    path, so both give bit-identical windows and the per-sample cost is a copy into a ring.
    """

    def __init__(self, spec: FeatureSpec, offset: np.ndarray | None = None, derive: bool = True) -> None:
        self.spec = spec
        self._derive = spec.derive if derive else _identity
        """``derive=False``: windows of the filtered base columns (stage 5, [window * n_base]), left for the caller
        to derive; the detector then reads one filtered window for both its model and the contact state."""
        self._cols = np.array(spec.columns, dtype=np.intp)
        self._all_cols = spec.columns == tuple(range(N_PILLARS * 3))  # every column, in order: no selection
        self._clip = np.tile(CLIP_N, N_PILLARS)
        self._hist_len = spec.median - 1 + spec.window
        # Linear buffer twice the history: writes append, and a shift happens once per history
        # length, so the window is always a contiguous slice (no per-sample allocation).
        self._buf = np.zeros((2 * self._hist_len, spec.n_base), np.float32)
        self._last_good = np.zeros(N_PILLARS * 3, np.float32)
        self._scratch = np.zeros(N_PILLARS * 3, np.float32)
        self._abs = np.zeros(N_PILLARS * 3, np.float32)
        # A block's |tared| values and their in-range flags (``push_many``, blocks up to a window's worth).
        self._absk = np.zeros((spec.window + 1, N_PILLARS * 3), np.float32)
        self._ok = np.zeros((spec.window + 1, N_PILLARS * 3), bool)
        self._offset = np.zeros(N_PILLARS * 3, np.float32)  # written in place (``StreamGroup`` holds views of it)
        # The offset and the clip bound repeated for a block's rows: a ufunc over operands of one shape takes numpy's
        # fast loop, one that broadcasts a row costs several times more on a decision's block.
        self._offset_rows = np.zeros((spec.window + 1, N_PILLARS * 3), np.float32)
        self._clip_rows = np.tile(self._clip, (spec.window + 1, 1))
        self._block_rows: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}  # ``_rows_of``
        self.set_offset(offset)
        self.nonfinite_count = 0
        self.clipped_count = 0
        """Tared values beyond twice the sensor range (impossible readings, e.g. a 1e6 N glitch), clipped."""
        self.reset()

    def set_offset(self, offset: np.ndarray | None) -> None:
        """Replace the tare offset ([9, 3], or None for zero). Takes effect from the next sample."""
        self._offset[:] = 0.0 if offset is None else np.asarray(offset, np.float32).reshape(-1)
        self._offset_rows[:] = self._offset
        self.offset_z = self._offset[2::3].copy()
        """The normal forces' offsets [9] (the contact gate tares one sample per window with them)."""

    def reset(self) -> None:
        """Forget the history (after a reconnect or a gap): the next sample restarts the stream."""
        self._n = 0  # samples since reset
        self._end = 0  # one past the newest row in _buf
        self._last_good[:] = 0.0

    @property
    def samples_seen(self) -> int:
        """Samples pushed since the last reset."""
        return self._n

    def push(self, force: np.ndarray) -> np.ndarray | None:
        """Add one raw sample ([9, 3] or [27]); return the flattened window if one ends here, else None.

        The returned array is a fresh copy owned by the caller.
        """
        s = self._scratch
        s[:] = np.asarray(force, dtype=np.float32).reshape(-1)
        bad = ~np.isfinite(s)
        if bad.any():
            self.nonfinite_count += int(bad.sum())
            s[bad] = self._last_good[bad]
        self._last_good[:] = s
        np.subtract(s, self._offset, out=s)
        np.abs(s, out=self._abs)
        if (self._abs > self._clip).any():
            self.clipped_count += int(np.count_nonzero(self._abs > self._clip))
        np.clip(s, -self._clip, self._clip, out=s)
        row = s[self._cols]
        spec = self.spec
        if self._n == 0:
            # Edge padding: the history starts as copies of the first sample.
            self._buf[: spec.median - 1] = row
            self._end = spec.median - 1
        if self._end == len(self._buf):
            keep = self._hist_len - 1
            self._buf[:keep] = self._buf[self._end - keep : self._end]
            self._end = keep
        self._buf[self._end] = row
        self._end += 1
        self._n += 1
        n = self._n
        if n < spec.window or (n - spec.window) % spec.step:
            return None
        return self._window(self._buf[self._end - self._hist_len : self._end])

    def _window(self, hist: np.ndarray) -> np.ndarray:
        """The flattened window that ends a history slice, a fresh array the caller owns: the median's output is one
        (width 1 reads the history itself: copied)."""
        out: np.ndarray = self._derive(causal_median_tail(hist, self.spec.median)).reshape(-1)
        return out.copy() if self.spec.median == 1 else out

    def push_many(self, samples: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """Add a block of raw samples ([k, 9, 3] or [k, 27]) at once; ``push`` for each, in one pass.

        Returns ``(i, window)`` for each sample ``samples[i]`` that ends a window, in order: the same
        windows, bit for bit, and the same counters as k calls of ``push`` (sanitise, tare and clip run
        as one vectorised call per block; the median runs once per window, as in ``push``). Each window
        is a fresh copy owned by the caller.
        """
        x = np.asarray(samples, dtype=np.float32).reshape(-1, N_PILLARS * 3)
        k = len(x)
        if k == 0:
            return []
        if self._n and k <= len(self._ok) and self._end + k > len(self._buf):
            self._shift()  # (the block's rows then fit after the history, which the common block needs)
        if self._n and self._end + k <= len(self._buf):
            # The common block (a stream under way, room in the history): its prepared rows go straight into the
            # history, every window's median reads them there. The same values as below, fewer copies.
            rows = self._buf[self._end : self._end + k]
            small = k <= len(self._ok)
            if small:
                offset, absk, clip, ok = self._rows_of(k)
            else:
                offset = self._offset
            if self._all_cols:
                y = np.subtract(x, offset, out=rows)
            else:
                y = np.subtract(x, offset)
            # Every value finite and within the clip (NaN fails the comparison), over kept scratch arrays: no zero byte
            # among the flags (a byte search; ndarray.all goes through a Python wrapper that costs more than the
            # comparison on a decision's block).
            if small:
                within = np.less_equal(np.abs(y, out=absk), clip, out=ok)
            else:
                within = np.abs(y) <= self._clip
            if 0 not in within.tobytes():
                if not self._all_cols:
                    np.take(y, self._cols, axis=1, out=rows)
                return self._windows_in_place(x, k)
        y = x - self._offset
        if not (np.abs(y) <= self._clip).all():
            # Something to sanitise or clip (NaN fails the comparison too): the full sequence of push's
            # stages. The common block (finite, in range) needs neither and skips them: same values.
            x = x.copy()
            bad = ~np.isfinite(x)
            if bad.any():
                self.nonfinite_count += int(bad.sum())
                _hold_from(x, bad, self._last_good)
            y = np.subtract(x, self._offset)
            over = np.abs(y) > self._clip
            if over.any():
                self.clipped_count += int(np.count_nonzero(over))
            np.clip(y, -self._clip, self._clip, out=y)
        self._last_good[:] = x[-1]
        rows = y.take(self._cols, axis=1)
        spec = self.spec
        if self._n == 0:
            self._buf[: spec.median - 1] = rows[0]
            self._end = spec.median - 1
        n0 = self._n
        first = first_window_end(n0, spec)
        out = []
        done = 0
        for i in range(first, k, spec.step):
            self._append(rows[done : i + 1])
            done = i + 1
            hist = self._buf[self._end - self._hist_len : self._end]
            out.append((i, self._window(hist)))
        self._append(rows[done:])
        self._n = n0 + k
        return out

    def _rows_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first ``k`` rows of the block buffers (``block_views``)."""
        return block_views(self._block_rows, k, self._offset_rows, self._absk, self._clip_rows, self._ok)

    def _windows_in_place(self, x: np.ndarray, k: int) -> list[tuple[int, np.ndarray]]:
        """``push_many`` once the block's ``k`` prepared rows are in the history after its end: the windows they end."""
        spec = self.spec
        self._last_good[:] = x[-1]
        n0, end = self._n, self._end
        first = first_window_end(n0, spec)
        out = []
        for i in range(first, k, spec.step):
            hist = self._buf[end + i + 1 - self._hist_len : end + i + 1]
            out.append((i, self._window(hist)))
        self._end = end + k
        self._n = n0 + k
        return out

    def _append(self, rows: np.ndarray) -> None:
        """Append prepared rows to the history; fewer than ``window + 1`` at a time (one window's worth)."""
        m = len(rows)
        if self._end + m > len(self._buf):
            self._shift()
        self._buf[self._end : self._end + m] = rows
        self._end += m

    def _shift(self) -> None:
        """Move the history to the buffer's start, keeping what the next window's median needs (the same rows push
        keeps when it shifts)."""
        keep = self._hist_len - 1
        self._buf[:keep] = self._buf[self._end - keep : self._end]
        self._end = keep


class StreamGroup:
    """The feature streams of several sensors that see the same samples (the fingers of one gripper: both arrays
    arrive in the same frames), their histories side by side in one buffer, so the common block runs stages 2-5 once
    for all of them (``push_many``).

    Each stream stays a ``FeatureStream`` of its own: its history, offset and last finite values are views into the
    group's arrays, and everything that concerns one sensor (the start-up tare, a block to sanitise or clip, a restart)
    runs on that stream as before. Every stage is elementwise per column, so the group's windows are the streams' own,
    bit for bit. The streams must select every column in order (``FeatureSpec.columns`` all 27: the shipped model's
    derived layout), so that a history column is a raw column."""

    def __init__(self, streams: Sequence[FeatureStream]) -> None:
        self.streams = list(streams)
        first = self.streams[0]
        if any(st.spec != first.spec or not st._all_cols for st in self.streams):
            raise ValueError("a stream group needs streams of one spec that select every column")
        ns, nb = len(self.streams), first.spec.n_base
        self._buf = np.zeros((len(first._buf), ns * nb), np.float32)
        self._offset = np.zeros((ns, nb), np.float32)
        self._last_good = np.zeros((ns, nb), np.float32)
        for s, st in enumerate(self.streams):
            cols = slice(s * nb, (s + 1) * nb)
            self._buf[:, cols] = st._buf
            st._buf = self._buf[:, cols]
            self._offset[s] = st._offset
            st._offset = self._offset[s]
            self._last_good[s] = st._last_good
            st._last_good = self._last_good[s]
        # Each stream's offset repeated for a block's rows (``FeatureStream._offset_rows``), side by side: a stream's
        # ``set_offset`` writes its columns here.
        self._offset_rows = np.zeros((first.spec.window + 1, ns * nb), np.float32)
        for s, st in enumerate(self.streams):
            self._offset_rows[:, s * nb : (s + 1) * nb] = st._offset_rows
            st._offset_rows = self._offset_rows[:, s * nb : (s + 1) * nb]
            st._block_rows.clear()  # (views of the buffer replaced here)
        self._clip_rows = np.tile(first._clip, (first.spec.window + 1, ns))
        self._absk = np.zeros((first.spec.window + 1, ns * nb), np.float32)
        self._ok = np.zeros((first.spec.window + 1, ns * nb), bool)
        self._block_rows: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def _rows_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first ``k`` rows of the group's side-by-side block buffers (``block_views``)."""
        return block_views(self._block_rows, k, self._offset_rows, self._absk, self._clip_rows, self._ok)

    def push_many(self, samples: np.ndarray) -> list[tuple[int, np.ndarray]] | None:
        """A block of raw samples [k, S, 9, 3] into every stream at once: ``(i, windows)`` for each sample
        ``samples[i]`` that ends a window, ``windows`` the streams' filtered windows side by side ([window, S * n_base],
        stream ``s`` in columns ``s * n_base ..``; each stream's ``push_many`` returns the same values), and each stream
        advanced as its own ``push_many`` would. None, with nothing pushed, unless the block is the common one (the
        streams under way in lockstep, every value finite and within the clip): push it stream by stream then."""
        streams = self.streams
        first = streams[0]
        k = len(samples)
        n0 = first._n
        if not n0 or k > len(self._ok):
            return None
        end = first._end
        for st in streams:
            if st._n != n0 or st._end != end:
                return None
        if end + k > len(self._buf):
            for st in streams:  # (the same rows of every column: one shift would do, but each stream keeps its end)
                st._shift()
            end = first._end
        x = samples.reshape(k, -1)
        rows = self._buf[end : end + k]
        offset, absk, clip, ok = self._rows_of(k)
        y = np.subtract(x, offset, out=rows)
        within = np.less_equal(np.abs(y, out=absk), clip, out=ok)
        if 0 in within.tobytes():  # (some value beyond the clip or not finite: ``FeatureStream.push_many``'s test)
            return None  # (the rows written after the histories' end are written again by each stream's push)
        self._last_good[:] = x[-1].reshape(self._last_good.shape)
        spec = first.spec
        hist_len, width = first._hist_len, spec.median
        start = first_window_end(n0, spec)
        out = []
        for i in range(start, k, spec.step):
            hist = self._buf[end + i + 1 - hist_len : end + i + 1]
            out.append((i, causal_median_tail(hist, width).copy() if width == 1 else sliding_median(hist, width)))
        for st in streams:
            st._end = end + k
            st._n = n0 + k
        return out


def block_views(cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], k: int,
                *buffers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first ``k`` rows of four block buffers (offset, |tared| scratch, clip bound, in-range flags), kept in
    ``cache``: views made once per block length (a decision's reads are one length, stride frames), not four slices
    per block."""
    views = cache.get(k)
    if views is None:
        a, b, c, d = buffers
        views = cache[k] = (a[:k], b[:k], c[:k], d[:k])
    return views


def first_window_end(n0: int, spec: FeatureSpec) -> int:
    """The first index ``i`` of a block pushed after ``n0`` samples whose sample ends a window: the count
    ``n0 + i + 1`` reaches the window, then every step."""
    first = max(spec.window - 1 - n0, 0)
    return first + (-(n0 + first + 1 - spec.window) % spec.step)


def _identity(filtered: np.ndarray) -> np.ndarray:
    return filtered


def _hold_from(x: np.ndarray, bad: np.ndarray, last: np.ndarray) -> None:
    """In place: replace non-finite ``x`` entries by the last finite value of their column, ``last`` before row 0."""
    k, c = x.shape
    src = np.where(bad, 0, np.arange(1, k + 1)[:, None])  # row in [last; x] that holds the value to use
    np.maximum.accumulate(src, axis=0, out=src)
    x[:] = np.concatenate([last[None, :], x])[src, np.arange(c)[None, :]]


def causal_median_tail(hist: np.ndarray, width: int) -> np.ndarray:
    """Median filter outputs for the last ``len(hist) - width + 1`` samples of ``hist`` (no padding)."""
    if width == 1:
        return hist
    return sliding_median(hist, width)


def stream_windows(force: np.ndarray, spec: FeatureSpec, offset: np.ndarray | None = None) -> list[np.ndarray]:
    """Run ``FeatureStream`` over a recording (for tests and replay); returns the windows in order."""
    fs = FeatureStream(spec, offset)
    out = []
    for sample in np.asarray(force):
        w = fs.push(sample)
        if w is not None:
            out.append(w)
    return out


def pillar_order_doc(pillars: Sequence[int]) -> str:
    """Human-readable description of a pillar order, for manifests and model cards."""
    return ", ".join(f"P{p}" for p in pillars)
