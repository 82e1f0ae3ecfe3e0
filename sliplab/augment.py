"""The method's training augmentations, applied to raw sequences BEFORE the feature pipeline.

Every function here takes and returns a ``Seq``: tared forces [N, 9, 3] (offset already removed,
so an unloaded pillar reads ~0 N), the [N] window-label source and the optional [N, 9] per-pillar
slip truth. Filtering and windowing are always left to ``slipd.detect.features`` afterwards, so augmented
training data passes through exactly the code the daemon runs.

Why tared forces: removing the offset commutes with the pipeline's first stages (holding the last
finite value, then subtracting a constant), so ``batch_windows(force - offset, spec, None)`` equals
``batch_windows(force, spec, offset)`` bit for bit, and it makes the physical augmentations
meaningful: a rotated, scaled or "unloaded" pillar is rotated, scaled or zeroed around its unloaded
reading, not around an arbitrary sensor bias. It also keeps the tare stretch valid after samples are
dropped or pillars are mixed from different recordings.

Augmentations (names used by ``tools/train.py --aug``):
    rotation   ``rotate_forces``: every (fx, fy) pair of a sequence rotated by one theta ~ U[0, 2 pi).
               This is the method's version. It rotates the force vectors only, not the pillar
               positions, so it is not an exact physical symmetry of the 3x3 array (a rotated sensor
               would also move its pillars; the shorter corner pillars would land on edge positions
               unless theta is a multiple of 90 degrees). ``rotate_grid_90`` is the exact symmetry
               for multiples of 90 degrees (positions permuted AND vectors rotated); it is offered
               as the extra augmentation ``grid90``.
    speed      ``drop_samples``: drop a fraction of samples (rates 0, 0.1, 0.2, 0.3, 0.4), keep the
               1 kHz spacing; labels and slip truth are dropped alongside.
    unloaded   ``unload_pillars``: with p = 0.2 replace 1..3 pillars (all three axes) by N(0, 0.001 N).
    mixing     ``mix_pillars``: nine pillar sequences from different recordings, some scaled by a
               factor in [0.2, 2.0], at permuted positions; the label is recomputed from the slip
               truth of the pillars used (``label_from_slip``).
    shapes     ``contact_shape``: with p = 0.25 only the pillars of one contact shape stay loaded (a line of
               three, a cross, a 2x2 block, an L): the contacts of curved objects, edges and small objects,
               which load two to five pillars where a flat object loads nine.
    slow       ``stretch``: with p = 0.3 the sequence played 1.5 to 3 times slower (linear interpolation, fresh
               sensor noise on top): loads that grow and slips that spread over seconds, where our families'
               lifts and pushes take tenths of one.
    sensor     ``sensor_model``: each pillar's axes scaled by their own gain in [0.8, 1.25], its normal force
               leaking into its tangential axes by up to 3 %, and a one-pole low-pass with a random corner
               (120 Hz to none): another sensor's calibration, cross-talk and filtering.
    friction   ``friction_scale``: with p = 0.5 every pillar's tangential force scaled by one factor,
               log-uniform in [0.5, 4]: the same grasp on a surface with that much more or less friction. A
               sliding pillar's |Ft| / Fz sits at its friction coefficient, and our families' slips sit near
               0.1 (the gripper trials) and 0.5-0.8 (the hexapod families); objects elsewhere slide anywhere
               from 0.2 to above 1, so the onset must be read from how the pillars' loads move, not from where.
    zero       ``zero_offset``: with p = 0.5 every pillar's zero off by a constant, N(0, s x one sample's noise) per
               axis with s in [0.5, 2]: a bias taken from few samples, or a pillar that drifted after it. A light
               grasp's outer pillars carry a few tenths of a newton, so such an offset moves their friction
               utilisation as much as their load does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slipd.geometry import N_PILLARS, OUTER, PILLAR_XY_MM

SPEED_RATES = (0.0, 0.1, 0.2, 0.3, 0.4)
"""The method's sample-drop rates for speed variation."""
UNLOADED_SIGMA_N = 0.001
"""Noise of an unloaded pillar in the method (N)."""
CONTACT_SHAPES = (
    (1, 4, 7), (3, 4, 5), (0, 1, 2), (0, 3, 6), (2, 5, 8), (6, 7, 8), (0, 4, 8), (2, 4, 6),
    (1, 3, 4, 5, 7), (0, 1, 3, 4), (1, 2, 4, 5), (3, 4, 6, 7), (4, 5, 7, 8), (0, 1, 2, 3, 6), (4, 5), (1, 4),
)
"""Pillars a contact loads when it is not flat (SDK raster order, centre 4): lines of three (a cylinder, an edge),
a cross (a sphere on the tallest pillars), 2x2 blocks (a small object off centre), an L, and pairs."""


@dataclass
class Seq:
    """One training sequence before the feature pipeline (tared forces, labels, optional slip truth)."""

    force: np.ndarray
    """[N, 9, 3] float32, offset removed."""
    label: np.ndarray
    """[N] uint8, 1 = incipient slip."""
    slip: np.ndarray | None = None
    """[N, 9] bool per-pillar sliding truth, or None when the recording has none."""
    loaded: np.ndarray | None = None
    """[9] bool: False where a pillar was replaced by unloaded noise (None = all loaded)."""

    def __post_init__(self) -> None:
        n = len(self.force)
        if self.force.shape != (n, N_PILLARS, 3):
            raise ValueError(f"force must be [N, 9, 3], got {self.force.shape}")
        if self.label.shape != (n,):
            raise ValueError(f"label must be [{n}], got {self.label.shape}")
        if self.slip is not None and self.slip.shape != (n, N_PILLARS):
            raise ValueError(f"slip must be [{n}, 9], got {self.slip.shape}")

    def __len__(self) -> int:
        return len(self.force)


def label_from_slip(slip: np.ndarray, considered: Sequence[int] = OUTER) -> np.ndarray:
    """The method's labelling rule: incipient slip (1) while some but not all considered pillars slip.

    ``slip`` is [N, 9] bool; ``considered`` lists the pillars that count (the outer eight by default:
    the centre pillar never slips under rotation). With no considered pillar the label is all 0.
    """
    cols = np.asarray(list(considered), dtype=np.intp)
    if cols.size == 0:
        return np.zeros(len(slip), np.uint8)
    n_slip = np.asarray(slip, bool)[:, cols].sum(axis=1)
    return ((n_slip > 0) & (n_slip < cols.size)).astype(np.uint8)


def rotate_forces(seq: Seq, theta: float) -> Seq:
    """Rotate every (fx, fy) pair by ``theta`` radians (the method's rotation augmentation).

    fz, labels and slip truth are unchanged; per-pillar tangential magnitude is preserved.
    """
    c, s = np.cos(theta), np.sin(theta)
    f = seq.force.copy()
    fx, fy = seq.force[..., 0], seq.force[..., 1]
    f[..., 0] = c * fx - s * fy
    f[..., 1] = s * fx + c * fy
    return Seq(f.astype(np.float32, copy=False), seq.label, seq.slip, seq.loaded)


def grid90_permutation(k: int) -> np.ndarray:
    """``perm`` such that after rotating the sensor by k * 90 degrees, new pillar j holds old pillar perm[j]."""
    ang = k * np.pi / 2
    c, s = np.cos(ang), np.sin(ang)
    rotated = PILLAR_XY_MM @ np.array([[c, s], [-s, c]])  # row i: old pillar i's position after rotation
    perm = np.empty(N_PILLARS, np.intp)
    for i, xy in enumerate(rotated):
        j = int(np.argmin(np.linalg.norm(PILLAR_XY_MM - xy, axis=1)))
        perm[j] = i
    return perm


def rotate_grid_90(seq: Seq, k: int) -> Seq:
    """Exact symmetry of the array: rotate positions and force vectors by k * 90 degrees.

    The slip truth moves with its pillar; the label is unchanged (the outer ring maps onto itself).
    """
    perm = grid90_permutation(k % 4)
    rotated = rotate_forces(seq, k * np.pi / 2)
    slip = None if seq.slip is None else seq.slip[:, perm]
    loaded = None if seq.loaded is None else seq.loaded[perm]
    return Seq(np.ascontiguousarray(rotated.force[:, perm]), seq.label, slip, loaded)


def drop_samples(seq: Seq, rate: float, rng: np.random.Generator) -> Seq:
    """Drop a fraction ``rate`` of samples at random (keeping order and the 1 kHz spacing).

    The result has ``len(seq) - round(rate * len(seq))`` samples; labels and slip truth are dropped
    alongside so every kept sample keeps its own label.
    """
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"drop rate must be in [0, 1), got {rate}")
    n = len(seq)
    n_drop = round(rate * n)
    if n_drop == 0:
        return seq
    keep = np.sort(rng.choice(n, size=n - n_drop, replace=False))
    slip = None if seq.slip is None else seq.slip[keep]
    return Seq(seq.force[keep], seq.label[keep], slip, seq.loaded)


def shift_start(seq: Seq, max_shift: int, rng: np.random.Generator) -> Seq:
    """Drop the first r ~ U{0, ..., max_shift - 1} samples so windows fall at a random phase.

    At run time the daemon can decide every ``window / k`` samples with k phase-shifted GRU streams
    (``slipd.detect.detector``); each stream sees windows cut at a different phase of the same motion. Without
    this, every training window starts at a multiple of the window length from the recording start.
    """
    if max_shift <= 1 or len(seq) <= max_shift:
        return seq
    r = int(rng.integers(0, max_shift))
    if r == 0:
        return seq
    slip = None if seq.slip is None else seq.slip[r:]
    return Seq(seq.force[r:], seq.label[r:], slip, seq.loaded)


def unload_pillars(
    seq: Seq,
    rng: np.random.Generator,
    p: float = 0.2,
    n_range: tuple[int, int] = (1, 3),
    sigma: float = UNLOADED_SIGMA_N,
    considered: Sequence[int] = OUTER,
) -> Seq:
    """With probability ``p`` replace 1..3 pillars (fx, fy, fz) by N(0, sigma) noise.

    An unloaded pillar touches nothing, so it cannot slip: its slip truth is cleared and, when the
    sequence has slip truth, the label is recomputed over the considered pillars still loaded.
    Without slip truth the label is kept (the method's version).
    """
    if rng.random() >= p:
        return seq
    k = int(rng.integers(n_range[0], n_range[1] + 1))
    chosen = rng.choice(N_PILLARS, size=k, replace=False)
    force = seq.force.copy()
    force[:, chosen, :] = rng.normal(0.0, sigma, size=(len(seq), k, 3)).astype(np.float32)
    loaded = np.ones(N_PILLARS, bool) if seq.loaded is None else seq.loaded.copy()
    loaded[chosen] = False
    if seq.slip is None:
        return Seq(force, seq.label, None, loaded)
    slip = seq.slip.copy()
    slip[:, chosen] = False
    label = label_from_slip(slip, [p_ for p_ in considered if loaded[p_]])
    return Seq(force, label, slip, loaded)


def mix_pillars(
    sources: Sequence[Seq],
    rng: np.random.Generator,
    scale_p: float = 0.5,
    scale_range: tuple[float, float] = (0.2, 2.0),
    considered: Sequence[int] = OUTER,
) -> Seq:
    """Build one sequence from nine pillar sequences of different recordings (the method's mixing).

    Each of the nine slots takes a random pillar of a different source (sources repeat only when
    fewer than nine are given), each slot is scaled by U[scale_range] with probability ``scale_p``,
    and the slots are placed at a random permutation of the pillar positions. All sources are cut to
    the shortest one. Every source needs slip truth: the label is recomputed with ``label_from_slip``
    over the considered positions, from the slip truth of the pillars placed there.
    """
    if not sources:
        raise ValueError("mix_pillars needs at least one source sequence")
    if any(s.slip is None for s in sources):
        raise ValueError("mix_pillars needs slip truth in every source (to recompute the label)")
    n = min(len(s) for s in sources)
    src = rng.choice(len(sources), size=N_PILLARS, replace=len(sources) < N_PILLARS)
    pillar = rng.integers(0, N_PILLARS, size=N_PILLARS)
    positions = rng.permutation(N_PILLARS)  # slot j goes to pillar position positions[j]
    scale = np.where(rng.random(N_PILLARS) < scale_p, rng.uniform(*scale_range, size=N_PILLARS), 1.0)
    force = np.empty((n, N_PILLARS, 3), np.float32)
    slip = np.empty((n, N_PILLARS), bool)
    loaded = np.ones(N_PILLARS, bool)
    for j in range(N_PILLARS):
        s = sources[src[j]]
        pos = positions[j]
        force[:, pos] = s.force[:n, pillar[j]] * np.float32(scale[j])
        slip[:, pos] = s.slip[:n, pillar[j]]  # type: ignore[index]
        if s.loaded is not None:
            loaded[pos] = s.loaded[pillar[j]]
    label = label_from_slip(slip, [p for p in considered if loaded[p]])
    return Seq(force, label, slip, loaded)


def contact_shape(seq: Seq, rng: np.random.Generator, p: float = 0.25, sigma: float = UNLOADED_SIGMA_N) -> Seq:
    """With probability ``p`` keep one ``CONTACT_SHAPES`` entry's pillars loaded and unload the rest.

    The unloaded pillars read N(0, sigma) and their slip truth is cleared. The label is kept from the first sample
    on which a pillar still loaded slides (the slip the label marks is then under way on the contact that is left);
    before it, and throughout when none of them ever slides, it is 0.
    """
    if rng.random() >= p:
        return seq
    keep = np.zeros(N_PILLARS, bool)
    keep[list(CONTACT_SHAPES[int(rng.integers(len(CONTACT_SHAPES)))])] = True
    force = seq.force.copy()
    force[:, ~keep, :] = rng.normal(0.0, sigma, size=(len(seq), int((~keep).sum()), 3)).astype(np.float32)
    loaded = keep if seq.loaded is None else (seq.loaded & keep)
    if seq.slip is None:
        return Seq(force, seq.label, None, loaded)
    slip = seq.slip.copy()
    slip[:, ~keep] = False
    sliding = slip.any(axis=1)
    label = seq.label.copy()
    first = int(np.argmax(sliding)) if sliding.any() else len(label)
    label[:first] = 0
    return Seq(force, label, slip, loaded)


def sensor_model(seq: Seq, rng: np.random.Generator, gain: tuple[float, float] = (0.8, 1.25),
                 crosstalk: float = 0.03, corner_hz: tuple[float, float] = (120.0, 500.0),
                 rate_hz: float = 1000.0) -> Seq:
    """Another sensor's calibration, cross-talk and filtering applied to one sequence (labels unchanged).

    Gains are drawn per pillar and axis (log-uniform in ``gain``); each pillar's tangential axes take up to
    ``crosstalk`` of its normal force; half of the sequences also pass a one-pole low-pass whose corner is drawn
    in ``corner_hz``.
    """
    lo, hi = np.log(gain[0]), np.log(gain[1])
    g = np.exp(rng.uniform(lo, hi, size=(N_PILLARS, 3))).astype(np.float32)
    force = seq.force * g
    c = rng.uniform(-crosstalk, crosstalk, size=(N_PILLARS, 2)).astype(np.float32)
    force[:, :, :2] += force[:, :, 2:3] * c
    if rng.random() < 0.5 and len(force):
        from scipy.signal import lfilter

        fc = float(rng.uniform(*corner_hz))
        a = 1.0 - np.exp(-2.0 * np.pi * fc / rate_hz)
        # Started at rest on the first sample, so the filter adds no step of its own.
        force = lfilter([a], [1.0, a - 1.0], force, axis=0, zi=(1.0 - a) * force[:1])[0]
    return Seq(np.asarray(force, np.float32), seq.label, seq.slip, seq.loaded)


FRICTION_GAIN = (0.5, 4.0)
"""Range of the friction augmentation's tangential gain (log-uniform)."""


def friction_scale(seq: Seq, rng: np.random.Generator, p: float = 0.5,
                   gain: tuple[float, float] = FRICTION_GAIN) -> Seq:
    """With probability ``p``, every pillar's tangential force scaled by one gain (labels unchanged).

    One gain for the whole sequence and every pillar keeps the grasp's own mechanics (which pillars load first,
    which slide) and moves only the friction coefficient at which they slide.
    """
    if rng.random() >= p:
        return seq
    g = np.float32(np.exp(rng.uniform(np.log(gain[0]), np.log(gain[1]))))
    force = seq.force.copy()
    force[:, :, :2] *= g
    return Seq(force, seq.label, seq.slip, seq.loaded)


SENSOR_NOISE_N = (0.03, 0.015)
"""One sample's noise, normal and tangential (the upper bounds of the PapillArray's, ``papillarray.md``)."""


def zero_errors(rng: np.random.Generator, sigma: tuple[float, float], draws: int) -> np.ndarray:
    """[draws, 9, 3] float32: each pillar's zero error, N(0, sigma_t) on x and y, N(0, sigma_z) on z."""
    scale = np.array([sigma[1], sigma[1], sigma[0]], np.float64)
    return (rng.standard_normal((draws, 9, 3)) * scale).astype(np.float32)


ZERO_SCALE = (0.5, 2.0)
"""Range of the zero augmentation's error, in samples of the sensor's noise (``SENSOR_NOISE_N``), uniform."""


def zero_offset(seq: Seq, rng: np.random.Generator, p: float = 0.5, scale: tuple[float, float] = ZERO_SCALE) -> Seq:
    """With probability ``p``, every reading of the sequence offset by one zero error per pillar and axis (labels
    unchanged): a zero taken that much off, as ``sliplab.zero_error`` measures the detector under it.

    The sequence is tared already, so the whole of it moves: the error is the zero's, not a step within the grasp.
    """
    if rng.random() >= p:
        return seq
    s = float(rng.uniform(*scale))
    e = zero_errors(rng, (s * SENSOR_NOISE_N[0], s * SENSOR_NOISE_N[1]), 1)[0]
    return Seq(seq.force - e, seq.label, seq.slip, seq.loaded)


STRETCH_NOISE_N = 0.008
"""Noise added after interpolating a stretched sequence (N): interpolation averages the sensor's own noise away."""


def stretch(seq: Seq, rng: np.random.Generator, p: float = 0.3, factor: tuple[float, float] = (1.5, 3.0)) -> Seq:
    """With probability ``p`` play the sequence ``U[factor]`` times slower at the same 1 kHz spacing.

    Forces are interpolated linearly between samples; each new sample takes the label and slip truth of the
    original sample it falls in; fresh noise (``STRETCH_NOISE_N``) replaces the noise the interpolation smoothed.
    """
    n = len(seq)
    if n < 2 or rng.random() >= p:
        return seq
    f = float(rng.uniform(*factor))
    m = int((n - 1) * f) + 1
    x = np.arange(m) / f
    i0 = np.minimum(np.floor(x).astype(np.intp), n - 2)
    w = (x - i0).astype(np.float32)[:, None, None]
    force = seq.force[i0] * (1.0 - w) + seq.force[i0 + 1] * w
    force += rng.normal(0.0, STRETCH_NOISE_N, size=force.shape).astype(np.float32)
    near = np.minimum(np.round(x).astype(np.intp), n - 1)
    slip = None if seq.slip is None else seq.slip[near]
    return Seq(force.astype(np.float32), seq.label[near], slip, seq.loaded)
