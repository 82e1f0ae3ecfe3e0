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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from slipd.geometry import CONTACT_THRESHOLD_N, FT_RANGE_N, FZ_RANGE_N, N_PILLARS, OUTER

CHANNEL_INDEX = {"fx": 0, "fy": 1, "fz": 2}
DERIVED = ("util", "lutil", "ux", "uy", "gft", "gfz", "gutil", "rspeed")
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
gutil |Ft| / max(Fz, floor), the floor the contact threshold or the grasp's mean pillar load (its summed Fz over the
      spec's pillars), whichever is lower, and at least ``GUTIL_MIN_N``: util on a firm grasp, while on a light
      one (pillars of 0.1-0.4 N) a sliding pillar reads its friction coefficient instead of |Ft| / 0.5 N. With
      util, a light grasp sliding on 0.2 N pillars at a friction of 0.8 reads 0.3, as a firm grasp at a third of
      its limit does.
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
GUTIL_MIN_N = np.float32(0.05)
"""Lowest floor of ``gutil`` (about two samples of a pillar's normal-force noise): free air reads near 0."""
CLIP_N = np.array([2 * FT_RANGE_N, 2 * FT_RANGE_N, 2 * FZ_RANGE_N], dtype=np.float32)
"""Bound on tared forces per axis (twice the sensor's range)."""
KEPT_CHANNELS = (("util",), ("gutil",), ("gutil", "gfz"))
"""Channel lists that ``derive`` runs as a few kept numpy calls (``FeatureSpec.util_ops``): one utilisation alone, or
``gutil`` with the contact's spread beside it (the shipped model's layout)."""


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
    if channel == "gutil":
        return float(np.hypot(CLIP_N[0], CLIP_N[1]) / GUTIL_MIN_N)
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

    def derive(self, filtered: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Stage 5b: [T, n_base] filtered samples -> [T, n_channels]; the identity without derived channels. Written
        into ``out`` ([T, n_channels]) where given (the feature stream's derived rows), else a new array (or
        ``filtered`` itself, the identity).

        Elementwise float32 arithmetic per sample, so any split of a recording into pieces gives the same
        values bit for bit (the streaming and batch paths both call this). A ``windowed`` spec takes whole
        windows, ``T`` a multiple of ``window`` (one window, or several stacked).
        """
        if not self.derived:
            if out is None:
                return filtered
            out[...] = filtered
            return out
        if self.channels in KEPT_CHANNELS:
            # (``out`` not one block of memory, a stream's columns of a group's rows: its reshape would be a copy)
            contiguous = out is not None and out.flags.c_contiguous
            res = out if out is not None and contiguous else np.empty((len(filtered), self.n_channels), filtered.dtype)
            run_ops(self.util_ops(filtered, res.reshape(-1), np.empty(res.size, filtered.dtype),
                                  np.empty((3, filtered.size // self.n_base), filtered.dtype)))
            if out is not None and not contiguous:
                out[...] = res
                return out
            return res
        f = filtered.reshape(len(filtered), len(self.pillars), 3)
        fz = np.maximum(f[:, :, 2], _UTIL_FLOOR_F32)
        res = self._derive_parts(f, fz)
        if out is None:
            return res
        out[...] = res
        return out

    def util_ops(self, filtered: np.ndarray, out: np.ndarray, fz: np.ndarray, grasp: np.ndarray) -> list[Op]:
        """``derive``'s calls for a model on ``KEPT_CHANNELS`` (util alone, gutil alone, or gutil and gfz) on
        [T, n_base] filtered samples (or [T, S * n_base], the rows of S sensors side by side, each a row of its own),
        into ``out`` [T * S * n_channels] with ``fz`` of at least T * S * pillars values for the floored normal forces
        and, for gutil, ``grasp`` [3, T * S] for each row's load, floor and (gfz) floored load (``out`` and, where the
        calls are kept, ``filtered`` one block of memory each). The axes as one-dimensional views, one row per pillar
        and sample: numpy's loop over a strided two-dimensional operand costs twice the arithmetic on a block's rows.
        The same calls on the same values as ``_derive_parts``, so the same values bit for bit."""
        p = filtered.reshape(-1, 3)
        fz = fz[: len(p)]

        def ratio(dst: np.ndarray) -> list[Op]:  # |Ft| over the floored Fz, one value per pillar and row
            return [(np.hypot, p[:, 0], p[:, 1], dst), (np.divide, dst, fz, dst)]

        if self.channels == ("util",):
            return [(np.maximum, p[:, 2], _UTIL_FLOOR_F32, fz), *ratio(out)]
        # gutil: the floor is the grasp's mean pillar load within [GUTIL_MIN_N, the contact threshold]
        pillars, width = len(self.pillars), len(self.channels)
        # (pillar-major: each pillar's channels side by side)
        gutil = out if width == 1 else out.reshape(-1, width)[:, 0]
        pz = filtered.reshape(-1, pillars, 3)[:, :, 2]
        load, floor = grasp[0, : len(pz)], grasp[1, : len(pz)]
        ops: list[Op] = [(np.add.reduce, pz, 1, load), (np.divide, load, np.float32(pillars), floor),
                         (np.maximum, floor, GUTIL_MIN_N, floor), (np.minimum, floor, _UTIL_FLOOR_F32, floor),
                         (np.maximum, pz, floor[:, None], fz.reshape(-1, pillars)), *ratio(gutil)]
        if width == 2:  # gfz: each pillar's share of the grasp's load, floored at the contact threshold
            total = grasp[2, : len(pz)]
            ops += [(np.maximum, load, _UTIL_FLOOR_F32, total),
                    (np.divide, pz, total[:, None], out.reshape(-1, pillars, width)[:, :, 1])]
        return ops

    def _derive_parts(self, f: np.ndarray, fz: np.ndarray) -> np.ndarray:
        """``derive`` of [T, P, 3] filtered forces and their floored normal forces, channel by channel."""
        parts = []
        util = np.hypot(f[:, :, 0], f[:, :, 1]) / fz if {"util", "lutil"} & set(self.channels) else fz
        load = f[:, :, 2].sum(axis=1, keepdims=True)  # the grasp's normal load over the spec's pillars
        grasp = np.maximum(load, np.float32(UTIL_FLOOR_N))
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
            elif c == "gutil":
                floor = np.clip(load / np.float32(len(self.pillars)), GUTIL_MIN_N, _UTIL_FLOOR_F32)
                parts.append(np.hypot(f[:, :, 0], f[:, :, 1]) / np.maximum(f[:, :, 2], floor))
            elif c == "rspeed":
                parts.append(self._rspeed(f))
            else:
                parts.append(f[:, :, CHANNEL_INDEX[c]])
        return np.stack(parts, axis=-1).astype(np.float32, copy=False).reshape(len(f), self.n_channels)

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


Op = tuple[Callable[..., Any], Any, Any, Any]
"""One numpy call ``f(a, b, out=out)`` of a stage, its operands views made once (``run_ops``)."""


def run_ops(ops: Sequence[Op]) -> None:
    """Make the calls of a stage, in order. (``out`` by keyword: a ufunc's positional ``out`` costs twice the call.)"""
    for f, a, b, o in ops:
        f(a, b, out=o)


def sliding_median(hist: np.ndarray, width: int, out: np.ndarray | None = None) -> np.ndarray:
    """Median of every run of ``width`` consecutive rows of ``hist`` [M, C] -> [M - width + 1, C] float32, written
    into ``out`` where given (otherwise a new array).

    An odd-width median is one of its inputs, so any exact method gives the same bits. Widths 3 and 5
    (the shipped model's) use min/max selection networks over shifted views (``median_ops``): about a hundred times
    faster than ``np.median`` over a sliding view, which dominated the cost of a training epoch; other odd widths (the
    heuristics' 21) a partial sort that puts the middle value in place (``np.partition``: ``np.median``'s selection
    without its generic reductions, 2 to 7 times faster); even widths ``np.median`` (the mean of the middle two).
    The rows are finite here: the pipeline bridges non-finite values before it filters.
    """
    n = len(hist) - width + 1
    if width == 1:
        if out is None:
            return hist.astype(np.float32)
        out[...] = hist
        return out
    if width in (3, 5):
        res = np.empty((n, *hist.shape[1:]), hist.dtype) if out is None else out
        run_ops(median_ops(hist, width, res, np.empty((4, n + 2, *hist.shape[1:]), hist.dtype)))
        return res.astype(np.float32, copy=False)
    runs = sliding_window_view(hist, width, axis=0)
    if width % 2:
        mid = width // 2
        med: np.ndarray = np.partition(runs, mid, axis=-1)[..., mid].astype(np.float32, copy=False)
    else:
        med = np.median(runs, axis=-1).astype(np.float32)
    if out is None:
        return med
    out[...] = med
    return out


def median_ops(hist: np.ndarray, width: int, out: np.ndarray, scratch: np.ndarray) -> list[Op]:
    """``sliding_median``'s calls for width 3 or 5, into ``out`` [len(hist) - width + 1, C], with ``scratch`` [4, at
    least len(hist) - width + 3, C] for the intermediate values: the one implementation of the median networks, which
    the batch path runs once and the feature streams keep for the rows a block filters (this runs once per block on the
    daemon's hot path, where the number of numpy calls and views sets the cost, not the rows)."""
    n = len(hist) - width + 1
    if width == 3:
        # median3(a, b, c) = max(min(a, b), min(max(a, b), c))
        a, b, c = hist[0:n], hist[1 : n + 1], hist[2 : n + 2]
        t1, t2 = scratch[0, :n], scratch[1, :n]
        return [(np.minimum, a, b, t1), (np.maximum, a, b, t2), (np.minimum, t2, c, t2), (np.maximum, t1, t2, out)]
    if width != 5:
        raise ValueError(f"median networks are of width 3 or 5, not {width}")
    # median5 = median3(e, max(min(a, b), min(c, d)), min(max(a, b), max(c, d))) of the rows a..e of each run: the
    # larger of the two pair minima and the smaller of the two pair maxima bracket the median of a..d's middle pair. A
    # pair (a, b) is two consecutive rows, and so is (c, d), two rows further: one minimum and one maximum of every two
    # consecutive rows serve both pairs.
    m = n + 2
    pair_min, pair_max, lo, hi = scratch[0, :m], scratch[1, :m], scratch[2, :n], scratch[3, :n]
    h0, h1, e = hist[0:m], hist[1 : m + 1], hist[4 : n + 4]
    t = pair_max[0:n]  # (written once ``hi`` has read it)
    return [(np.minimum, h0, h1, pair_min), (np.maximum, h0, h1, pair_max),
            (np.maximum, pair_min[0:n], pair_min[2 : n + 2], lo), (np.minimum, pair_max[0:n], pair_max[2 : n + 2], hi),
            # median3(e, lo, hi) = max(min(e, lo), min(max(e, lo), hi)), as width 3 computes it
            (np.maximum, e, lo, t), (np.minimum, t, hi, t), (np.minimum, e, lo, lo), (np.maximum, lo, t, out)]


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

    Memory is constant: a history of prepared samples (stages 1-4), their filtered rows (stage 5) and their derived
    rows (stage 5b), each in a linear buffer twice a window's history long. When a window completes, the median and
    the derived channels are computed for the rows it holds that no earlier window computed (a decision every
    ``stride`` samples filters and derives ``stride`` rows, not the whole window), with the same functions as the
    batch path (``sliding_median``, ``FeatureSpec.derive``): elementwise per sample, so the windows are bit-identical
    to ``batch_windows``'. A ``windowed`` spec derives each window whole, from its filtered rows.
    """

    def __init__(self, spec: FeatureSpec, offset: np.ndarray | None = None) -> None:
        self.spec = spec
        self._cols = np.array(spec.columns, dtype=np.intp)
        self._all_cols = spec.columns == tuple(range(N_PILLARS * 3))  # every column, in order: no selection
        self._clip = np.tile(CLIP_N, N_PILLARS)
        self._hist_len = spec.median - 1 + spec.window
        # Linear buffers twice the history: writes append, and a shift happens once per history
        # length, so the window is always a contiguous slice (no per-sample allocation).
        rows = 2 * self._hist_len
        self._buf = np.zeros((rows, spec.n_base), np.float32)
        # Row r of ``_filt`` is the median of the prepared rows r - median + 1 .. r (rows before ``_done`` computed
        # where a window needs them); ``_der`` the derived channels of ``_filt``'s row r (``_filt`` itself without
        # derived channels, None where they are derived window by window).
        self._filt = self._buf if spec.median == 1 else np.zeros_like(self._buf)
        self._der: np.ndarray | None = self._filt
        if spec.derived:
            self._der = None if spec.windowed else np.zeros((rows, spec.n_channels), np.float32)
        self._plans = RowPlans(spec, self._buf, self._filt, self._der)
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
        self.clean = False
        """The latest ``push_views`` (or ``push_many``) took the common block: every value finite and within the clip,
        so nothing was sanitised, clipped or counted. The loop reads it instead of checking the block's values for
        finiteness a second time (``slipd.daemon.loop``). False after a ``push`` and after a block with something to
        sanitise or clip."""
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
        self._done = 0  # one past the newest row of _filt and _der computed
        self._last_good[:] = 0.0

    @property
    def samples_seen(self) -> int:
        """Samples pushed since the last reset."""
        return self._n

    def samples_to_window(self) -> int:
        """Samples still to push until the next one that completes a window (1: the very next one)."""
        n, w, step = self._n, self.spec.window, self.spec.step
        return w - n if n < w else step - (n - w) % step

    def push(self, force: np.ndarray) -> np.ndarray | None:
        """Add one raw sample ([9, 3] or [27]); return the flattened window if one ends here, else None.

        The returned array is a fresh copy owned by the caller (``filtered`` holds the window's filtered rows).
        """
        self.clean = False
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
            self._shift()
        self._buf[self._end] = row
        self._end += 1
        self._n += 1
        n = self._n
        if n < spec.window or (n - spec.window) % spec.step:
            return None
        return self._window(self._end - spec.window, self._end)[0].copy()

    def filtered(self) -> np.ndarray:
        """The filtered rows [window, n_base] of the latest window ``push`` returned (a view, valid until the next
        push)."""
        return self._filt[self._end - self.spec.window : self._end]

    def _window(self, lo: int, e: int) -> tuple[np.ndarray, np.ndarray]:
        """The window that ends before row ``e``, its rows from ``lo`` on computed (stages 5, 5b): the flattened model
        window [input_size] and the filtered rows [window, n_base], views of the buffers (a ``windowed`` spec's model
        window a new array)."""
        self._filter(lo, e)
        model, filt, _ = self._plans.window(e)
        return model, filt

    def _filter(self, lo: int, e: int) -> None:
        """Stages 5 and 5b on the rows ``lo .. e - 1`` that are not computed yet."""
        lo = max(lo, self._done)
        if lo < e:
            run_ops(self._plans.ops(lo, e))
            self._done = e

    def push_many(self, samples: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """Add a block of raw samples ([k, 9, 3] or [k, 27]) at once; ``push`` for each, in one pass.

        Returns ``(i, window)`` for each sample ``samples[i]`` that ends a window, in order: the same
        windows, bit for bit, and the same counters as k calls of ``push``. Each window is a fresh copy owned by the
        caller.
        """
        return [(i, w.copy()) for i, w, _, _ in self.push_views(samples)]

    def push_views(self, samples: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]:
        """``push_many`` with each window's filtered rows: ``(i, window, filtered, prepared)``, the flattened model
        window [input_size], the filtered rows [window, n_base] (the contact state's) and, in the common block (every
        value finite and within the clip, so stages 1-4 changed nothing but the tare), the prepared row of the window's
        last sample [n_base] (its tared values: the contact gate's), else None. Views of the stream's buffers, valid
        until the next push (copies where the block is too long for that).

        Sanitise, tare and clip run as one vectorised call per block; the median and the derived channels once per
        block too, on the rows the block's windows need.
        """
        x = np.asarray(samples, dtype=np.float32).reshape(-1, N_PILLARS * 3)
        k = len(x)
        self.clean = False
        if k == 0:
            return []
        if self._n and k <= len(self._ok) and self._end + k > len(self._buf):
            self._shift()  # (the block's rows then fit after the history, which the common block needs)
        if self._n and self._end + k <= len(self._buf):
            # The common block (a stream under way, room in the history): its prepared rows go straight into the
            # history, every window reads them there. The same values as below, fewer copies.
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
                self._last_good[:] = x[-1]
                self.clean = True
                return self._advance(k)
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
        out: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = []
        done = 0
        for i in range(first, k, spec.step):
            self._append(rows[done : i + 1])
            done = i + 1
            # (copies: a later window's rows may shift the buffers)
            w, f = self._window(self._end - spec.window, self._end)
            out.append((i, w.copy(), f.copy(), None))
        self._append(rows[done:])
        self._n = n0 + k
        return out

    def _rows_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first ``k`` rows of the block buffers (``block_views``)."""
        return block_views(self._block_rows, k, self._offset_rows, self._absk, self._clip_rows, self._ok)

    def _advance(self, k: int) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]:
        """``push_views`` once the block's ``k`` prepared rows are in the history after its end: the windows they end,
        their rows filtered and derived in one pass."""
        spec = self.spec
        n0, end = self._n, self._end
        first = first_window_end(n0, spec)
        self._end = end + k
        self._n = n0 + k
        if first >= k:
            return []
        ends = range(end + first + 1, end + k + 1, spec.step)
        self._filter(ends[0] - spec.window, ends[-1])
        window = self._plans.window
        return [(e - end - 1, *window(e)) for e in ends]

    def _append(self, rows: np.ndarray) -> None:
        """Append prepared rows to the history; fewer than ``window + 1`` at a time (one window's worth)."""
        m = len(rows)
        if self._end + m > len(self._buf):
            self._shift()
        self._buf[self._end : self._end + m] = rows
        self._end += m

    def _shift(self) -> None:
        """Move the history to the buffers' start, keeping what the next window needs (the same rows push keeps when
        it shifts)."""
        self._end, self._done = shift_rows(history_buffers(self._buf, self._filt, self._der), self._end, self._done,
                                           self._hist_len - 1)


def history_buffers(buf: np.ndarray, filt: np.ndarray, der: np.ndarray | None) -> list[np.ndarray]:
    """A history's buffers (one row per sample): prepared, filtered, derived, each once (without a median the
    filtered rows are the prepared ones; without derived channels the derived rows are the filtered ones)."""
    out = [buf]
    if filt is not buf:
        out.append(filt)
    if der is not None and der is not filt:
        out.append(der)
    return out


def shift_rows(buffers: Sequence[np.ndarray], end: int, done: int, keep: int) -> tuple[int, int]:
    """Move the last ``keep`` rows before ``end`` of each buffer to its start; the new end and computed-rows mark."""
    a = end - keep
    for b in buffers:
        b[:keep] = b[a:end]
    return keep, max(done - a, 0)


class RowPlans:
    """Stages 5 and 5b on a range of rows of a history's buffers (prepared ``buf``, filtered ``filt``, derived ``der``,
    one row per sample; ``FeatureStream``), and the windows they end, as numpy calls and views made once per range and
    kept: a block at a decision's stride lands on one of a few positions of the buffers, so each block runs a list of
    prepared calls (``median_ops``, ``FeatureSpec.util_ops``) instead of making a few dozen views and numpy calls anew.
    Bounded: at most ``MAX_KEPT`` ranges are kept (then the lists start anew)."""

    MAX_KEPT = 256

    def __init__(self, spec: FeatureSpec, buf: np.ndarray, filt: np.ndarray, der: np.ndarray | None) -> None:
        self.spec = spec
        self.buf, self.filt, self.der = buf, filt, der
        self._scratch = np.zeros((4, len(buf), buf.shape[1]), np.float32)  # (the median's intermediate values)
        self._fz = np.zeros(len(buf) * (0 if der is None else der.shape[1]), np.float32)  # (util's floored Fz)
        self._grasp = np.zeros((3, buf.size // spec.n_base), np.float32)  # (gutil's load, floor, gfz's load per row)
        self._ops: dict[tuple[int, int], list[Op]] = {}
        self._windows: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def ops(self, lo: int, e: int) -> list[Op]:
        """The calls that filter and derive rows ``lo .. e - 1`` (the median reads the prepared rows from
        ``lo - median + 1`` on)."""
        ops = self._ops.get((lo, e))
        if ops is not None:
            return ops
        if len(self._ops) >= self.MAX_KEPT:
            self._ops.clear()
        spec, buf, filt, der = self.spec, self.buf, self.filt, self.der
        width = spec.median
        ops = []
        if filt is not buf:
            hist = buf[lo + 1 - width : e]
            if width in (3, 5):
                ops += median_ops(hist, width, filt[lo:e], self._scratch)
            else:
                ops.append((sliding_median, hist, width, filt[lo:e]))
        if der is not None and der is not filt:
            f, d = filt[lo:e], der[lo:e]
            if spec.channels in KEPT_CHANNELS and f.flags.c_contiguous and d.flags.c_contiguous:
                ops += spec.util_ops(f, d.reshape(-1), self._fz[: d.size], self._grasp)
            else:
                # (sample by sample: rows of several sensors side by side are rows of their own to ``derive``)
                ops.append((_derive_into, spec, f, d))
        self._ops[(lo, e)] = ops
        return ops

    def window(self, e: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The window that ends before row ``e``: the model's (flattened, [input_size]; a ``windowed`` spec's derived
        anew), its filtered rows [window, n_base] and the prepared row of its last sample, views of the buffers."""
        views = self._windows.get(e)
        if views is None:
            if len(self._windows) >= self.MAX_KEPT:
                self._windows.clear()
            start = e - self.spec.window
            filt = self.filt[start:e]
            if self.der is None:
                return self.spec.derive(filt).reshape(-1), filt, self.buf[e - 1]
            der = self.der[start:e]
            if not der.flags.c_contiguous:  # (a stream's columns of a group's rows: flattened, a copy, not kept)
                return der.reshape(-1), filt, self.buf[e - 1]
            views = self._windows[e] = (der.reshape(-1), filt, self.buf[e - 1])
        return views


def _derive_into(spec: FeatureSpec, filtered: np.ndarray, *, out: np.ndarray) -> None:
    """``spec.derive(filtered, out)`` on rows of one or several sensors side by side (each ``n_base`` columns)."""
    spec.derive(filtered.reshape(-1, spec.n_base), out=out.reshape(-1, spec.n_channels) if out.flags.c_contiguous
                else out)


class StreamGroup:
    """The feature streams of several sensors that see the same samples (the fingers of one gripper: both arrays
    arrive in the same frames), their histories side by side in one buffer, so the common block runs stages 2-5b once
    for all of them (``push_views``).

    Each stream stays a ``FeatureStream`` of its own: its histories, offset and last finite values are views into the
    group's arrays, and everything that concerns one sensor (the start-up tare, a block to sanitise or clip, a restart)
    runs on that stream as before. Every stage is elementwise per column (per sample for the derived channels), so the
    group's windows are the streams' own, bit for bit. The streams must select every column in order
    (``FeatureSpec.columns`` all 27: the shipped model's derived layout), so that a history column is a raw column,
    and derive sample by sample (not ``windowed``)."""

    def __init__(self, streams: Sequence[FeatureStream]) -> None:
        self.streams = list(streams)
        first = self.streams[0]
        if any(st.spec != first.spec or not st._all_cols for st in self.streams) or first.spec.windowed:
            raise ValueError("a stream group needs streams of one spec that select every column and derive per sample")
        ns, nb = len(self.streams), first.spec.n_base
        same_filt, same_der = first._filt is first._buf, first._der is first._filt  # (no median; no derived channels)
        self._buf = self._side_by_side("_buf")
        self._filt = self._buf if same_filt else self._side_by_side("_filt")
        self._der = self._filt if same_der else self._side_by_side("_der")
        for st in self.streams:
            if same_filt:
                st._filt = st._buf
            if same_der:
                st._der = st._filt
            st._plans = RowPlans(st.spec, st._buf, st._filt, st._der)  # (on its views of the group's buffers)
        self._plans = RowPlans(first.spec, self._buf, self._filt, self._der)
        self._offset = np.zeros((ns, nb), np.float32)
        self._last_good = np.zeros((ns, nb), np.float32)
        for s, st in enumerate(self.streams):
            self._offset[s] = st._offset
            st._offset = self._offset[s]
            self._last_good[s] = st._last_good
            st._last_good = self._last_good[s]
        # Each stream's offset repeated for a block's rows (``FeatureStream._offset_rows``), side by side: a stream's
        # ``set_offset`` writes its columns here.
        self._offset_rows = self._side_by_side("_offset_rows")
        for st in self.streams:
            st._block_rows.clear()  # (views of the buffer replaced here)
        self._clip_rows = np.tile(first._clip, (first.spec.window + 1, ns))
        self._absk = np.zeros((first.spec.window + 1, ns * nb), np.float32)
        self._ok = np.zeros((first.spec.window + 1, ns * nb), bool)
        self._block_rows: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    def _side_by_side(self, name: str) -> np.ndarray:
        """One array of the streams' buffers ``name`` side by side (stream ``s`` in the ``s``-th block of columns),
        each stream's buffer replaced by its view of it."""
        parts = [getattr(st, name) for st in self.streams]
        both = np.concatenate(parts, axis=1)
        c = parts[0].shape[1]
        for s, st in enumerate(self.streams):
            setattr(st, name, both[:, s * c : (s + 1) * c])
        return both

    def _rows_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first ``k`` rows of the group's side-by-side block buffers (``block_views``)."""
        return block_views(self._block_rows, k, self._offset_rows, self._absk, self._clip_rows, self._ok)

    def push_views(self, samples: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] | None:
        """A block of raw samples [k, S, 9, 3] into every stream at once: ``(i, windows, filtered, prepared)`` for each
        sample ``samples[i]`` that ends a window, ``windows`` the streams' model windows side by side (flattened
        [window, S * n_channels], stream ``s`` in columns ``s * n_channels ..``), ``filtered`` their filtered rows
        ([window, S * n_base]) and ``prepared`` the prepared rows of the window's last sample ([S * n_base]: the tared
        values), views valid until the next push (each stream's ``push_views`` gives the same values), and each
        stream advanced as its own ``push_views`` would. None, with nothing pushed, unless the block is the common one
        (the streams under way in lockstep, every value finite and within the clip): push it stream by stream then."""
        streams = self.streams
        first = streams[0]
        k = len(samples)
        n0 = first._n
        if not n0 or k > len(self._ok):
            return None
        end = first._end
        done = first._done
        for st in streams:
            if st._n != n0 or st._end != end:
                return None
            if st._done < done:
                done = st._done
        if end + k > len(self._buf):
            end, done = shift_rows(history_buffers(self._buf, self._filt, self._der), end, done, first._hist_len - 1)
            for st in streams:
                st._end, st._done = end, done
        x = samples.reshape(k, -1)
        rows = self._buf[end : end + k]
        offset, absk, clip, ok = self._rows_of(k)
        y = np.subtract(x, offset, out=rows)
        within = np.less_equal(np.abs(y, out=absk), clip, out=ok)
        if 0 in within.tobytes():  # (some value beyond the clip or not finite: ``FeatureStream.push_many``'s test)
            return None  # (the rows written after the histories' end are written again by each stream's push)
        self._last_good[:] = x[-1].reshape(self._last_good.shape)
        spec = first.spec
        start = first_window_end(n0, spec)
        for st in streams:
            st._end = end + k
            st._n = n0 + k
            st.clean = True
        if start >= k:
            return []
        ends = range(end + start + 1, end + k + 1, spec.step)
        lo = max(ends[0] - spec.window, done)
        e = ends[-1]
        if lo < e:
            run_ops(self._plans.ops(lo, e))
            for st in streams:
                st._done = e
        window = self._plans.window
        return [(e - end - 1, *window(e)) for e in ends]


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


def _hold_from(x: np.ndarray, bad: np.ndarray, last: np.ndarray) -> None:
    """In place: replace non-finite ``x`` entries by the last finite value of their column, ``last`` before row 0."""
    k, c = x.shape
    src = np.where(bad, 0, np.arange(1, k + 1)[:, None])  # row in [last; x] that holds the value to use
    np.maximum.accumulate(src, axis=0, out=src)
    x[:] = np.concatenate([last[None, :], x])[src, np.arange(c)[None, :]]


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
