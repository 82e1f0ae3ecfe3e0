"""Train the method's GRU ensemble (Z members, bootstrap subsets, the method's augmentations).

    python tools/train.py --data DIR --out DIR [--members 5] [--epochs N] [--seed S] [--tiny]
                          [--no-advanced-aug] [--aug rotation,speed,unloaded,mixing] [--overwrite] ...

What one member does per epoch:
    1. bootstrap: draw ``lambda`` = 40 % of the recordings with replacement (re-drawn every epoch);
    2. augment the raw (tared) sequences with ``sliplab.augment`` (mixed sequences are added on top);
    3. features through ``slipd.detect.features.batch_windows`` (the daemon's own pipeline) and window
       labels through ``window_labels``;
    4. truncated BPTT in "lanes": the epoch's sequences are packed end to end into B parallel lanes
       (B = batch // chunk, so one optimiser step sees ``batch`` windows). Each lane is stepped through
       time ``chunk`` windows (9 = 360 samples, as the released code cuts sequences) per step; the
       hidden state starts at zero at every sequence start, exactly as at run time, is carried across
       chunk boundaries and detached there (gradients flow back at most ``chunk`` windows). Carrying
       h instead of resetting it per chunk means the network is trained on the long hidden-state
       histories it meets in the daemon, which never resets h within a stream.
    5. SGD, momentum 0.95, lr 1e-3, weight decay 1e-3, batch 512 windows, cross-entropy on the
       logits (``SlipNet.logits``: the softmax is applied by the loss).

Choices the method leaves open (flags in brackets):
    - augmentations are drawn afresh every epoch for every sequence instead of materialising a fixed
      x5 augmented copy of the data set: rotation always (theta ~ U[0, 2 pi)), speed variation with a
      rate drawn from (0, 0.1, 0.2, 0.3, 0.4), unloaded pillars with p = 0.2, and ``mix_frac`` x the
      subset size extra mixed sequences built from the subset's recordings [--mix-frac 0.25];
    - "batch 512" is read as 512 windows per optimiser step (57 lanes x 9 windows) [--batch];
    - after the last epoch every member is run once in eval mode over the whole un-augmented data
      set, and its window metrics go into the log and the checkpoint (``eval``) [--no-eval];
    - optimiser: the method's SGD is the default; ``--optimizer adam`` and ``--lr`` exist for
      experiments. On the synthetic test data neither Adam (1e-3) nor SGD at lr 1e-2 learned faster
      than the method's setting within 10 epochs, so the defaults stay the method's.

Budget: ``FULL["epochs"]`` = 30 keeps the default 5-member ensemble on a few hundred 4 s recordings
under 30 minutes on 2 CPU cores (about 3.5 s per epoch on 300 x 4000-sample recordings when the
cores are free, most of it the causal median filter of ``slipd.detect.features``).

Outputs in ``--out``: ``member_<k>.pt`` per member (state_dict, config, feature_spec, provenance,
history, eval) written when the member finishes (a member whose file exists is skipped unless
``--overwrite``), and ``train_log.jsonl`` with one line per epoch and per finished member.
"""

from __future__ import annotations

import argparse
import heapq
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from slipd.detect.detector import gate_windows
from slipd.detect.features import FeatureSpec, batch_windows, stretch_offset, window_labels
from slipd.geometry import CONTACT_THRESHOLD_N
from slipd.recording import Recording, RecordingError, list_recordings
from sliplab.augment import (
    SPEED_RATES,
    Seq,
    contact_shape,
    drop_samples,
    friction_scale,
    mix_pillars,
    rotate_forces,
    rotate_grid_90,
    sensor_model,
    shift_start,
    stretch,
    unload_pillars,
    zero_offset,
)
from sliplab.model import SlipNet

ALL_AUGS = (
    "rotation", "speed", "unloaded", "mixing", "grid90", "shift", "shapes", "sensor", "slow", "friction", "zero",
)
DEFAULT_AUGS = ("rotation", "speed", "unloaded", "mixing")
ADVANCED_AUGS = ("unloaded", "mixing")

# Full-size defaults (the method) and the --tiny ones (tests, smoke runs): a flag given on the
# command line always wins over both.
FULL = {"members": 5, "epochs": 30, "enc": 1024, "hidden": 128, "pred": (256, 128), "batch": 512,
        "max_recordings": 0}
TINY = {"members": 2, "epochs": 2, "enc": 64, "hidden": 16, "pred": (32, 16), "batch": 64,
        "max_recordings": 8}


# ------------------------------------------------------------------------------------------ data
@dataclass
class Item:
    """One sequence after the feature pipeline: windows [K, D] float32, window labels [K] int64 and, where the
    simulator gave it, each window's per-pillar slip truth at its last sample [K, P] float32 (P = spec pillars)."""

    windows: np.ndarray
    labels: np.ndarray
    slip: np.ndarray | None = None


def slip_span_labels(label: np.ndarray, events: dict, t_s: np.ndarray) -> np.ndarray:
    """1 from the first incipient sample until the object has moved 2 mm / 2 deg (``gross_motion``).

    The method labels incipient slip only, so its network learns to stay silent once every pillar slides;
    yet an alarm then, before the object has moved far, is still in time for the robot (the online
    criterion). Without a ``gross_motion`` event (hexapod scenes) the span ends at ``gross_slip``, else at
    the last incipient sample. A stop trial (no incipient sample, no ``onset`` event) stays all 0. A slip with no
    incipient stage (every pillar in contact slides at once, as a light grasp's do: onset and gross slip on one
    sample, no labelled sample) runs from ``events["onset"]``; left at 0, it would teach that such a slide is no
    slip, while the online criterion counts it as one.
    """
    label = np.asarray(label)
    on = np.flatnonzero(label)
    end_t = events.get("gross_motion") or events.get("gross_slip")
    if len(on):
        # Only the first labelled run (the event the ``events`` describe) is extended: a recording with several
        # moves (press, slip, hold, release, regrasp, slip) keeps its holds between them negative.
        edges = np.flatnonzero(np.diff(np.concatenate([[0], (label > 0).astype(np.int8), [0]])))
        start, first_end = int(on[0]), int(edges[1])
        later = int(edges[2]) if len(edges) > 2 else len(label)
    elif events.get("onset") is not None and end_t is not None:
        start = int(np.searchsorted(t_s, events["onset"]))
        first_end, later = start + 1, len(label)
    else:
        return label
    end = int(np.searchsorted(t_s, end_t)) if end_t is not None else first_end
    out = label.copy()
    out[start : min(max(end, first_end), later)] = 1
    return out


SLIDING_GAP = 20
"""Samples without any sliding pillar that end a sliding span (shorter pauses are one stretch of sliding)."""


def sliding_span_labels(label: np.ndarray, slip: np.ndarray | None, events: dict, t_s: np.ndarray,
                        gap: int = SLIDING_GAP) -> np.ndarray:
    """1 from the onset of the first slip for as long as any pillar keeps sliding (pauses up to ``gap`` samples).

    An object that slides off the finger keeps sliding after the 2 mm of ``slip_span_labels``; under that span
    those windows teach that sliding is not slip. A slip with no incipient stage starts at ``events["onset"]``, as
    in ``slip_span_labels``. Never shorter than ``slip_span_labels``; without per-pillar truth (``slip`` None) it
    is that span.
    """
    out = slip_span_labels(label, events, t_s).astype(np.uint8)
    if slip is None:
        return out
    pos = np.flatnonzero(out)
    if not len(pos):
        return out
    start = int(pos[0])
    sliding = np.nan_to_num(np.asarray(slip, np.float64)).max(axis=1) > 0
    later_runs = np.flatnonzero(np.diff((out[start:] > 0).astype(np.int8)) > 0)
    stop_at = start + int(later_runs[0]) + 1 if len(later_runs) else len(out)  # a later labelled event stays its own
    seq = np.concatenate([[start - 1], start + np.flatnonzero(sliding[start:stop_at])])
    breaks = np.flatnonzero(np.diff(seq) - 1 > gap)  # quiet stretches longer than the gap
    last = int(seq[breaks[0]] if len(breaks) else seq[-1])
    out[start:max(last + 1, start + 1)] = 1
    return out


DEFAULT_FAMILY = "stick_slip"
"""The physics family of a recording whose meta names none (the offline and transfer sets)."""


def physics_family(rec: Recording) -> str:
    """The contact model a recording was simulated with (``meta["physics_family"]``)."""
    return str(rec.meta.get("physics_family", DEFAULT_FAMILY))


PARTIAL_SLIP_SAMPLES = 20
"""A recording without a labelled sample is a partial slip when a loaded pillar slides for this many samples."""


def is_partial_slip(label: np.ndarray, slip: np.ndarray | None, force: np.ndarray) -> bool:
    """No sample labelled slip, yet pillars in contact (tared normal force above the contact flag) slide for at least
    ``PARTIAL_SLIP_SAMPLES`` samples: a stop or hold in which part of the contact slid and stuck again."""
    if slip is None or np.asarray(label).any():
        return False
    sliding = (np.asarray(slip) & (np.asarray(force)[:, :, 2] > CONTACT_THRESHOLD_N)).any(axis=1)
    return int(sliding.sum()) >= PARTIAL_SLIP_SAMPLES


def load_sequences(data_dir: Path, spec: FeatureSpec, max_recordings: int = 0,
                   label_span: str = "incipient", exclude_families: tuple[str, ...] = (),
                   skip_partial: bool = False) -> tuple[list[Seq], list[str]]:
    """Load every recording under ``data_dir`` as a tared ``Seq``; returns (sequences, file names).

    The offset is the recording's own ``meta["tare_samples"]`` stretch (or ``spec.tare_samples``).
    A recording without labels, or too short for one window, raises ``RecordingError`` naming it.
    ``label_span`` "slip" extends each label with ``slip_span_labels``, "sliding" with ``sliding_span_labels``
    (the method: "incipient"). ``skip_partial`` leaves out the recordings ``is_partial_slip`` names: the engine's
    evaluation scores no outcome for them, while a training label of 0 teaches the members to wait out sliding.
    """
    paths = list_recordings(data_dir)
    if not paths:
        raise RecordingError(f"{data_dir}: no recordings (*.npz, *.csv)")
    if max_recordings > 0:
        paths = paths[:max_recordings]
    seqs, names = [], []
    for path in paths:
        rec = Recording.load(path)
        if physics_family(rec) in exclude_families:
            continue  # held out (leave-one-family-out)
        if rec.label is None:
            raise RecordingError(f"{path}: no 'label' array (training needs the incipient-slip truth)")
        if len(rec) < spec.window:
            raise RecordingError(f"{path}: {len(rec)} samples, fewer than one window ({spec.window})")
        tare = rec.meta.get("tare_samples", spec.tare_samples)
        try:
            offset = stretch_offset(rec.force, tare)
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"{path}: bad meta 'tare_samples' {tare!r} ({exc})") from exc
        # Taring here equals passing the offset to batch_windows (see tools/augment.py) and lets the
        # augmentations act around the unloaded reading.
        label = rec.label
        if label_span == "slip":
            label = slip_span_labels(label, rec.meta.get("events") or {}, rec.t_us / 1e6).astype(np.uint8)
        elif label_span == "sliding":
            label = sliding_span_labels(label, rec.slip, rec.meta.get("events") or {}, rec.t_us / 1e6)
        force = rec.force - offset
        if skip_partial and is_partial_slip(label, rec.slip, force):
            continue
        seqs.append(Seq(force, label, rec.slip))
        names.append(path.name)
    return seqs, names


def bootstrap_indices(n: int, frac: float, rng: np.random.Generator) -> np.ndarray:
    """``round(frac * n)`` (at least 1) indices into ``n`` sequences, drawn with replacement."""
    if n < 1:
        raise ValueError("bootstrap needs at least one sequence")
    return rng.integers(0, n, size=max(1, round(frac * n)))


def augment_epoch(
    pool: list[Seq], idx: np.ndarray, augs: set[str], rng: np.random.Generator, mix_frac: float,
    window: int = 40,
) -> list[Seq]:
    """The sequences of one epoch: the bootstrap subset plus mixed sequences, each augmented."""
    chosen = [pool[i] for i in idx]
    if "mixing" in augs:
        with_truth = np.unique([i for i in idx if pool[i].slip is not None])
        n_mix = round(mix_frac * len(idx))
        if len(with_truth) and n_mix:
            for _ in range(n_mix):
                pick = rng.choice(with_truth, size=min(9, len(with_truth)), replace=False)
                chosen.append(mix_pillars([pool[i] for i in pick], rng))
    out = []
    for seq in chosen:
        if "grid90" in augs:
            seq = rotate_grid_90(seq, int(rng.integers(0, 4)))
        if "rotation" in augs:
            seq = rotate_forces(seq, float(rng.uniform(0.0, 2 * np.pi)))
        if "unloaded" in augs:
            seq = unload_pillars(seq, rng)
        if "shapes" in augs:
            seq = contact_shape(seq, rng)
        if "sensor" in augs:
            seq = sensor_model(seq, rng)
        if "friction" in augs:
            seq = friction_scale(seq, rng)
        if "zero" in augs:
            seq = zero_offset(seq, rng)
        if "slow" in augs:
            seq = stretch(seq, rng)
        if "speed" in augs:
            seq = drop_samples(seq, float(rng.choice(SPEED_RATES)), rng)
        if "shift" in augs:
            seq = shift_start(seq, window, rng)
        out.append(seq)
    return out


def lead_labels(label: np.ndarray, lead: int) -> np.ndarray:
    """``label`` extended ``lead`` samples back in time: 1 where incipient slip starts within ``lead`` samples.

    A window is then positive when incipient slip is under way at its last sample (the method's rule) or
    begins within the next ``lead`` samples. Gripper trials hold incipient slip for a median of 28 ms,
    less than one window; the lead asks the network to flag the load pattern that precedes it.
    """
    label = np.asarray(label)
    if lead <= 0 or not label.any():
        return label
    padded = np.concatenate([label, np.zeros(lead, label.dtype)])
    win = np.lib.stride_tricks.sliding_window_view(padded, lead + 1)
    return win.max(axis=1)


def featurize(seqs: list[Seq], spec: FeatureSpec, lead: int = 0, gate: bool = True) -> list[Item]:
    """Run the daemon's feature pipeline on every sequence (offset already removed).

    With ``gate`` (the default, as the detector runs), each stretch the contact gate lets through
    (``slipd.detect.detector.gate_windows``) becomes its own item, so its first window meets h0 exactly as
    in the daemon; windows without contact are never shown to the model (the detector reports 0 there).
    """
    items = []
    for seq in seqs:
        windows, ends = batch_windows(seq.force, spec, None)
        if not len(ends):
            continue
        labels = window_labels(lead_labels(seq.label, lead), ends).astype(np.int64)
        slip = None if seq.slip is None else seq.slip[ends][:, list(spec.pillars)].astype(np.float32)
        if not gate:
            items.append(Item(windows, labels, slip))
            continue
        open_ = gate_windows(seq.force, spec)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], open_.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            items.append(Item(windows[a:b], labels[a:b], None if slip is None else slip[a:b]))
    return items


@dataclass
class Lanes:
    """Sequences packed end to end into B lanes of T windows."""

    x: torch.Tensor  # [B, T, D] float32
    y: torch.Tensor  # [B, T] int64
    valid: torch.Tensor  # [B, T] bool (False in the padding at a lane's end)
    keep: torch.Tensor  # [B, T] float32, 0 at the first window of a sequence (h resets), else 1
    slip: torch.Tensor | None = None  # [B, T, P] float32 per-pillar slip truth, NaN where a sequence has none


def pack_lanes(items: list[Item], n_lanes: int, rng: np.random.Generator | None = None) -> Lanes:
    """Pack ``items`` (in random order when ``rng`` is given) into at most ``n_lanes`` balanced lanes."""
    if not items:
        raise ValueError("no windows to train on (all sequences shorter than one window?)")
    order = rng.permutation(len(items)) if rng is not None else np.arange(len(items))
    n_lanes = max(1, min(n_lanes, len(items)))
    heap = [(0, b) for b in range(n_lanes)]
    lanes: list[list[int]] = [[] for _ in range(n_lanes)]
    for i in order:  # each sequence goes to the currently shortest lane
        total, b = heapq.heappop(heap)
        lanes[b].append(int(i))
        heapq.heappush(heap, (total + len(items[i].labels), b))
    t_max = max(total for total, _ in heap)
    dim = items[0].windows.shape[1]
    x = np.zeros((n_lanes, t_max, dim), np.float32)
    y = np.zeros((n_lanes, t_max), np.int64)
    valid = np.zeros((n_lanes, t_max), bool)
    keep = np.ones((n_lanes, t_max), np.float32)
    n_pillars = next((it.slip.shape[1] for it in items if it.slip is not None), 0)
    slip = np.full((n_lanes, t_max, n_pillars), np.nan, np.float32) if n_pillars else None
    for b, members in enumerate(lanes):
        t = 0
        for i in members:
            k = len(items[i].labels)
            x[b, t : t + k] = items[i].windows
            y[b, t : t + k] = items[i].labels
            valid[b, t : t + k] = True
            keep[b, t] = 0.0
            if slip is not None and items[i].slip is not None:
                slip[b, t : t + k] = items[i].slip
            t += k
    return Lanes(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(valid), torch.from_numpy(keep),
                 None if slip is None else torch.from_numpy(slip))


# ------------------------------------------------------------------------------------- training
def _chunk_logits(net: SlipNet, x: torch.Tensor, keep: torch.Tensor, valid: torch.Tensor, h: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Logits of the valid windows of one chunk ([B, L, D]), the hidden state after it, and the hidden state of
    every valid window (what the auxiliary head reads).

    Same computation as ``SlipNet.logits`` window by window; the encoder and the predictor run once
    on all valid windows of the chunk (they do not depend on h), the GRU steps through time.
    """
    b, length, dim = x.shape
    flat_valid = valid.reshape(-1)
    enc_valid = net.projector(x.reshape(-1, dim)[flat_valid])
    enc = enc_valid.new_zeros(b * length, enc_valid.shape[1])
    enc[flat_valid] = enc_valid
    enc = enc.view(b, length, -1)
    states = []
    for t in range(length):
        h = net.rnn(enc[:, t], h * keep[:, t, None])
        states.append(h)
    hs = torch.stack(states, 1).reshape(b * length, -1)[flat_valid]
    return net.predictor[:-1](hs), h, hs


def _counts(logits: torch.Tensor, y: torch.Tensor) -> np.ndarray:
    """[correct, true positives, predicted positives, actual positives] for incipient slip (class 1)."""
    pred = logits.argmax(1)
    return np.array([(pred == y).sum().item(), ((pred == 1) & (y == 1)).sum().item(),
                     (pred == 1).sum().item(), (y == 1).sum().item()], np.int64)


def _summary(loss_sum: float, n: int, c: np.ndarray) -> dict[str, float]:
    return {"loss": loss_sum / max(n, 1), "acc": c[0] / max(n, 1), "recall": c[1] / max(c[3], 1),
            "precision": c[1] / max(c[2], 1), "pos_frac": c[3] / max(n, 1), "windows": int(n)}


def run_ids(y: torch.Tensor, keep: torch.Tensor, chunk: int = 0) -> np.ndarray:
    """Ids [B, T] of the runs of positive windows, numbered through the lanes, -1 for negative windows. A run ends
    where a sequence starts (keep 0) and, with ``chunk``, at every truncated-BPTT chunk boundary."""
    pos = (y == 1).numpy()
    prev = np.concatenate([np.zeros((pos.shape[0], 1), bool), pos[:, :-1]], 1)
    start = pos & (~prev | (keep == 0).numpy())
    if chunk > 0:
        start |= pos & (np.arange(pos.shape[1]) % chunk == 0)[None, :]
    ids = np.cumsum(start.reshape(-1)).reshape(pos.shape) - 1
    return np.where(pos, ids, -1)


def early_weights(y: torch.Tensor, keep: torch.Tensor, windows: int, weight: float) -> torch.Tensor:
    """Per-window loss weights [B, T]: ``weight`` on the first ``windows`` windows of every run of positive
    windows, 1 elsewhere. Incipient slip lasts only a few windows before the object turns or falls; the plain
    loss is as happy with an alarm 60 ms into a run as with one 10 ms into it, and the online criterion is not."""
    out = torch.ones(y.shape, dtype=torch.float32)
    if windows <= 0 or weight == 1.0:
        return out
    ids = run_ids(y, keep).reshape(-1)
    pos = np.flatnonzero(ids >= 0)
    _, first = np.unique(ids[pos], return_index=True)  # each run's first window (ids 0, 1, ...; contiguous runs)
    into = pos - pos[first][ids[pos]]  # windows into the run
    out.view(-1)[torch.from_numpy(pos[into < windows])] = weight
    return out


def catch_runs(y: torch.Tensor, keep: torch.Tensor, chunk: int) -> torch.Tensor:
    """Run ids [B, T] for ``--catch`` (``run_ids``): a run that crosses a chunk boundary is two runs, because one
    optimiser step sees one chunk."""
    return torch.from_numpy(run_ids(y, keep, chunk))


def catch_loss(logits: torch.Tensor, runs: torch.Tensor) -> torch.Tensor:
    """Summed loss of the positive runs in ``runs`` (ids per window of ``logits``, -1 for negative windows):
    minus the log of the chance that at least one window of a run alarms, 1 - prod(1 - p), weighted by the run's
    length. The offline criterion asks for one alarm between a slip's onset and gross slip, not a high P(slip)
    in every window of it; per-window cross-entropy also punishes the windows of a run where the sensor shows
    little yet, which teaches members to stay low through a slip."""
    pos = runs >= 0
    if not pos.any():
        return logits.new_zeros(())
    ids, inverse, counts = torch.unique(runs[pos], return_inverse=True, return_counts=True)
    log_no = torch.log_softmax(logits[pos], 1)[:, 0]  # log(1 - p) per positive window
    total = log_no.new_zeros(len(ids)).index_add(0, inverse, log_no)
    # -log(1 - exp(total)); the clamp keeps the gradient finite where a run's windows all say "no slip" at p ~ 0
    return -(torch.log(-torch.expm1(total.clamp(max=-1e-6))) * counts).sum()


def train_epoch(net: SlipNet, opt: torch.optim.Optimizer, lanes: Lanes, chunk: int, clip_grad: float = 0.0,
                device: str = "cpu", pos_weight: float = 1.0, aux_weight: float = 0.0,
                early: tuple[int, float] = (0, 1.0), catch: bool = False) -> dict[str, float]:
    """One pass over packed lanes with truncated BPTT; returns mean loss and window metrics.

    ``pos_weight`` weighs the slip class in the loss: gripper trials hold incipient slip for only
    20-90 ms (one or two windows in a hundred), and an unweighted loss learns to never alarm.
    ``aux_weight`` adds the auxiliary head's per-pillar binary cross-entropy (windows with slip truth only).
    ``early`` (windows, weight): ``early_weights`` on the slip loss.
    ``catch``: the positive windows' loss is ``catch_loss`` per run (times ``pos_weight``) instead of
    per-window cross-entropy.
    """
    net.train()
    weight = None if pos_weight == 1.0 else torch.tensor([1.0, pos_weight], device=device)
    loss_fn = nn.CrossEntropyLoss(weight=weight, reduction="none")
    w_early = early_weights(lanes.y, lanes.keep, *early)
    runs = catch_runs(lanes.y, lanes.keep, chunk) if catch else None
    b, t_max, _ = lanes.x.shape
    h = torch.zeros(b, net.hidden, device=device)
    loss_sum, n_seen, counts = 0.0, 0, np.zeros(4, np.int64)
    for t0 in range(0, t_max, chunk):
        sl = slice(t0, t0 + chunk)
        valid = lanes.valid[:, sl].to(device)
        n = int(valid.sum())
        if n < 2:  # BatchNorm needs two rows; only the padded tail can be this short
            continue
        y = lanes.y[:, sl].to(device).reshape(-1)[valid.reshape(-1)]
        w_y = w_early[:, sl].to(device).reshape(-1)[valid.reshape(-1)]
        use_aux = aux_weight > 0 and net.aux_head is not None and lanes.slip is not None
        logits, h, hs = _chunk_logits(net, lanes.x[:, sl].to(device), lanes.keep[:, sl].to(device), valid, h)
        if runs is None:
            loss = (loss_fn(logits, y) * w_y).sum()
        else:
            loss = (loss_fn(logits, y) * w_y)[y == 0].sum() + pos_weight * catch_loss(
                logits, runs[:, sl].to(device).reshape(-1)[valid.reshape(-1)])
        if use_aux:
            truth = lanes.slip[:, sl].to(device).reshape(-1, lanes.slip.shape[-1])[valid.reshape(-1)]
            known = ~torch.isnan(truth)
            if known.any():
                aux = nn.functional.binary_cross_entropy_with_logits(
                    net.aux_head(hs)[known], truth[known], reduction="sum") / truth.shape[1]
                loss = loss + aux_weight * aux
        opt.zero_grad(set_to_none=True)
        (loss / n).backward()
        if clip_grad > 0:
            nn.utils.clip_grad_norm_(net.parameters(), clip_grad)
        opt.step()
        h = h.detach()
        loss_sum += float(loss.detach())
        n_seen += n
        counts += _counts(logits.detach(), y)
    return _summary(loss_sum, n_seen, counts)


@torch.no_grad()
def precise_bn(net: SlipNet, items: list[Item], n_lanes: int, chunk: int, device: str = "cpu") -> None:
    """Recompute every BatchNorm's running statistics as exact averages over ``items`` (no gradient).

    Training keeps them as an exponential average of the last batches, whose mix of quiet and moving
    windows changes from batch to batch; eval-mode outputs then drift and the slip probability ends up
    squeezed into a narrow band, so the alarm threshold becomes brittle. Averaging over the whole
    un-augmented data set once at the end ("precise BN") removes that drift. The GRU state is carried
    exactly as in training.
    """
    bns = [m for m in net.modules() if isinstance(m, nn.BatchNorm1d)]
    saved = [m.momentum for m in bns]
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # cumulative moving average: every batch weighs the same
    net.train()
    lanes = pack_lanes(items, n_lanes)
    b, t_max, _ = lanes.x.shape
    h = torch.zeros(b, net.hidden, device=device)
    for t0 in range(0, t_max, chunk):
        sl = slice(t0, t0 + chunk)
        valid = lanes.valid[:, sl].to(device)
        if int(valid.sum()) < 2:
            continue
        _, h, _ = _chunk_logits(net, lanes.x[:, sl].to(device), lanes.keep[:, sl].to(device), valid, h)
    for m, mom in zip(bns, saved):
        m.momentum = mom
    net.eval()


@torch.no_grad()
def evaluate(net: SlipNet, items: list[Item], device: str = "cpu") -> dict[str, float]:
    """Eval-mode window metrics, each sequence from h = 0 one window at a time (as the daemon runs)."""
    net.eval()
    lanes = pack_lanes(items, len(items))
    b, t_max, _ = lanes.x.shape
    h = torch.zeros(b, net.hidden, device=device)
    loss_fn = nn.CrossEntropyLoss(reduction="sum")
    loss_sum, n_seen, counts = 0.0, 0, np.zeros(4, np.int64)
    for t in range(t_max):
        valid = lanes.valid[:, t].to(device)
        z, h = net.logits(lanes.x[:, t].to(device), h)
        y = lanes.y[:, t].to(device)[valid]
        loss_sum += float(loss_fn(z[valid], y))
        n_seen += int(valid.sum())
        counts += _counts(z[valid], y)
    return _summary(loss_sum, n_seen, counts)


# ------------------------------------------------------------------------------------ provenance
def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None


def _index_summary(data_dir: Path) -> Any:
    """The data folder's ``index.json``, with long lists replaced by their length (None if absent)."""
    path = data_dir / "index.json"
    if not path.exists():
        return None
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return {"error": f"{path}: unreadable ({exc})"}
    if isinstance(index, dict) and isinstance(index.get("summary"), dict):
        return index["summary"]

    def shrink(v: Any) -> Any:
        if isinstance(v, list) and len(v) > 20:
            return {"items": len(v)}
        if isinstance(v, dict):
            return {k: shrink(w) for k, w in v.items()}
        return v

    return shrink(index)


def _jsonable(v: Any) -> Any:
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, (list, tuple)):
        return [_jsonable(w) for w in v]
    if isinstance(v, dict):
        return {k: _jsonable(w) for k, w in v.items()}
    if isinstance(v, np.generic):
        return v.item()  # numpy scalars would make torch.load(weights_only=True) refuse the checkpoint
    return v


# ------------------------------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command line; sizes left unset take the full (or --tiny) defaults."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, required=True, nargs="+", help="folder(s) of recordings (*.npz)")
    p.add_argument("--pillars", default="outer",
                   help="pillars feeding the model: 'outer' (the authors' 8, SDK P0-P3,P5-P8), 'all' (9), "
                        "or a comma list of SDK indices")
    p.add_argument("--out", type=Path, required=True, help="run directory for member_<k>.pt and train_log.jsonl")
    p.add_argument("--members", type=int, help="ensemble size Z (5)")
    p.add_argument("--epochs", type=int, help=f"epochs per member ({FULL['epochs']})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tiny", action="store_true", help="small model, 2 members, 2 epochs, 8 recordings (tests)")
    p.add_argument("--aug", default=",".join(DEFAULT_AUGS),
                   help=f"comma list among {','.join(ALL_AUGS)} (or 'none')")
    p.add_argument("--no-advanced-aug", action="store_true", help="switch off unloaded + mixing (the ablation)")
    p.add_argument("--mix-frac", type=float, default=0.25, help="mixed sequences added per epoch, as a fraction")
    p.add_argument("--bootstrap", type=float, default=0.4, help="lambda: fraction of sequences drawn per epoch")
    p.add_argument("--optimizer", choices=("sgd", "adam"), default="sgd")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--momentum", type=float, default=0.95)
    p.add_argument("--weight-decay", type=float, default=1e-3)
    p.add_argument("--lr-schedule", choices=("constant", "cosine"), default="constant",
                   help="cosine: the learning rate decays to 0 over the epochs (per epoch), so the last epochs "
                        "settle instead of ending wherever a noisy step left the weights")
    p.add_argument("--batch", type=int, help="windows per optimiser step (512)")
    p.add_argument("--chunk", type=int, default=9, help="windows per truncated-BPTT chunk (9 = 360 samples)")
    p.add_argument("--aux-weight", type=float, default=0.0,
                   help="weight of an auxiliary per-pillar slip head on the GRU state, trained on the simulator's "
                        "per-pillar slip truth (0 = off, the method; tools/export_onnx.py --pillar-head exports it)")
    p.add_argument("--pos-weight", type=float, default=1.0,
                   help="loss weight of the slip class (1 = the method's unweighted cross-entropy)")
    p.add_argument("--channels", default="fx,fy",
                   help="per-pillar channels, comma list among fx,fy,fz and the derived util (|Ft|/Fz) "
                        "and lutil (its log), see slipd.detect.features.DERIVED; the method: fx,fy")
    p.add_argument("--early-weight", type=float, default=1.0,
                   help="loss weight of the first --early-windows windows of every positive run (default 1: none)")
    p.add_argument("--early-windows", type=int, default=0,
                   help="how many windows from the start of each positive run --early-weight applies to")
    p.add_argument("--catch", action="store_true",
                   help="score each run of slip windows by the chance that at least one of them alarms "
                        "(sliplab.train.catch_loss), not window by window")
    p.add_argument("--label-span", choices=("incipient", "slip", "sliding"), default="incipient",
                   help="positive windows: incipient slip only (the method), from its onset until the object "
                        "has moved 2 mm / 2 deg (slip), or for as long as any pillar keeps sliding (sliding)")
    p.add_argument("--precise-bn", action="store_true",
                   help="after training, recompute BatchNorm statistics over the whole un-augmented data set")
    p.add_argument("--label-lead", type=int, default=0,
                   help="samples: also label a window positive when incipient slip starts this soon after it")
    p.add_argument("--window", type=int, default=40, help="samples per window (the method: 40)")
    p.add_argument("--median", type=int, default=21, help="causal median width, odd (the method: 21)")
    p.add_argument("--clip-grad", type=float, default=0.0, help="gradient norm clip (0 = off)")
    p.add_argument("--enc", type=int)
    p.add_argument("--tied-units", type=int, default=0,
                   help="units per pillar of an encoder with one set of weights for every pillar "
                        "(sliplab.model.PillarTiedLinear; exported in the dense layout, so --enc is ignored); "
                        "0 = the method's dense encoder")
    p.add_argument("--hidden", type=int)
    p.add_argument("--pred", type=int, nargs=2)
    p.add_argument("--max-recordings", type=int, help="use only the first N recordings (0 = all)")
    p.add_argument("--exclude-family", action="append", default=[],
                   help="leave out every recording of this physics family (meta physics_family; the offline and "
                        "transfer sets are stick_slip); repeatable: leave-one-family-out folds")
    p.add_argument("--skip-partial", action="store_true",
                   help="leave out recordings without a labelled sample in which loaded pillars slide for 20 ms or "
                        "more (stops and holds that slipped part way): the engine's evaluation scores no outcome "
                        "for such a recording")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-eval", action="store_true", help="skip the eval-mode pass over all data per member")
    p.add_argument("--overwrite", action="store_true", help="retrain members whose checkpoint exists")
    p.add_argument("--only", type=int, nargs="+",
                   help="train only these member indices (each member's randomness depends on --seed and its "
                        "index alone, so two processes with disjoint --only lists give the checkpoints one run "
                        "gives)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    defaults = TINY if args.tiny else FULL
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.pred = tuple(args.pred)
    augs = set() if args.aug.strip() in ("", "none") else {a.strip() for a in args.aug.split(",") if a.strip()}
    unknown = augs - set(ALL_AUGS)
    if unknown:
        p.error(f"--aug: unknown augmentation(s) {sorted(unknown)}; choose among {','.join(ALL_AUGS)}")
    if args.no_advanced_aug:
        augs -= set(ADVANCED_AUGS)
    args.augs = sorted(augs)
    if args.members < 1 or args.epochs < 1 or args.batch < 1 or args.chunk < 1:
        p.error("--members, --epochs, --batch and --chunk must be >= 1")
    if args.only is not None and not all(0 <= k < args.members for k in args.only):
        p.error(f"--only: member indices must be in 0..{args.members - 1}")
    if not 0 < args.bootstrap <= 1:
        p.error("--bootstrap must be in (0, 1]")
    return args


def pillars_arg(text: str) -> tuple[int, ...]:
    """``--pillars``: 'outer', 'all' or a comma list of SDK indices."""
    from slipd.geometry import N_PILLARS, OUTER

    if text == "outer":
        return OUTER
    if text == "all":
        return tuple(range(N_PILLARS))
    return tuple(int(x) for x in text.split(","))


def make_optimizer(net: SlipNet, args: argparse.Namespace) -> torch.optim.Optimizer:
    """SGD with momentum (the method) or Adam, both with L2 weight decay."""
    if args.optimizer == "adam":
        return torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    return torch.optim.SGD(net.parameters(), lr=args.lr, momentum=args.momentum, weight_decay=args.weight_decay)


def train_member(k: int, pool: list[Seq], eval_items: list[Item], spec: FeatureSpec, args: argparse.Namespace,
                 log: Any, progress: bool, names: list[str] | None = None) -> dict:
    """Train member ``k`` and return its checkpoint dict (also logs one line per epoch to ``log``)."""
    rng = np.random.default_rng([args.seed, k])
    torch.manual_seed(args.seed * 1000 + k)
    units = getattr(args, "tied_units", 0)
    tied = (spec.window, len(spec.pillars), len(spec.channels), units) if units > 0 else None
    net = SlipNet(spec.input_size, hidden=args.hidden, enc=args.enc, pred=args.pred,
                  aux=len(spec.pillars) if getattr(args, "aux_weight", 0.0) > 0 else 0, tied=tied).to(args.device)
    opt = make_optimizer(net, args)
    augs = set(args.augs)
    n_lanes = max(1, args.batch // args.chunk)
    history = []
    epochs: Any = range(args.epochs)
    if progress:
        from tqdm import tqdm

        epochs = tqdm(epochs, desc=f"member {k}", unit="epoch")
    t_member = time.perf_counter()
    for epoch in epochs:
        t0 = time.perf_counter()
        if getattr(args, "lr_schedule", "constant") == "cosine":
            for group in opt.param_groups:
                group["lr"] = args.lr * 0.5 * (1 + np.cos(np.pi * epoch / args.epochs))
        idx = bootstrap_indices(len(pool), args.bootstrap, rng)
        items = featurize(augment_epoch(pool, idx, augs, rng, args.mix_frac, spec.window), spec, args.label_lead)
        lanes = pack_lanes(items, n_lanes, rng)
        t_feat = time.perf_counter() - t0
        stats = train_epoch(net, opt, lanes, args.chunk, args.clip_grad, args.device, args.pos_weight,
                            getattr(args, "aux_weight", 0.0),
                            (getattr(args, "early_windows", 0), getattr(args, "early_weight", 1.0)),
                            getattr(args, "catch", False))
        entry = {"member": k, "epoch": epoch, **stats, "sequences": len(items),
                 "feature_s": round(t_feat, 3), "epoch_s": round(time.perf_counter() - t0, 3)}
        history.append(entry)
        log.write(json.dumps(entry) + "\n")
        log.flush()
        if progress:
            epochs.set_postfix(loss=f"{stats['loss']:.4f}", acc=f"{stats['acc']:.3f}", rec=f"{stats['recall']:.2f}")
    if args.precise_bn:
        precise_bn(net, featurize(pool, spec, args.label_lead), n_lanes, args.chunk, args.device)
    result: dict[str, Any] = {"member": k, "event": "done", "seconds": round(time.perf_counter() - t_member, 2)}
    if eval_items:
        result["eval"] = evaluate(net, eval_items, args.device)
    log.write(json.dumps(result) + "\n")
    log.flush()
    net.cpu().eval()
    return {"state_dict": net.dense_state_dict(), "config": net.config(), "feature_spec": spec.to_dict(),
            "provenance": {"data": [str(d) for d in args.data], "index": [_index_summary(d) for d in args.data],
                           "seed": args.seed,
                           "member": k, "args": _jsonable(vars(args)), "git": _git_commit(),
                           "recordings": names or []},
            "history": _jsonable(history), "eval": _jsonable(result.get("eval"))}


def main(argv: list[str] | None = None) -> int:
    """Train the ensemble described by the command line; returns the exit status."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    spec = FeatureSpec(pillars=pillars_arg(args.pillars), window=args.window, median=args.median,
                       channels=tuple(c.strip() for c in args.channels.split(",")))
    try:
        pool, names = [], []
        for folder in args.data:
            p, n = load_sequences(folder, spec, args.max_recordings, args.label_span, tuple(args.exclude_family),
                                  args.skip_partial)
            pool += p
            names += n
    except RecordingError as exc:
        print(f"train: {exc}", file=sys.stderr)
        return 2
    eval_items = [] if args.no_eval else featurize(pool, spec)
    args.out.mkdir(parents=True, exist_ok=True)
    progress = not args.quiet
    if progress:
        print(f"train: {len(pool)} recordings from {args.data}, augs {args.augs or 'none'}, "
              f"{args.members} members x {args.epochs} epochs -> {args.out}", file=sys.stderr)
    with open(args.out / "train_log.jsonl", "a") as log:
        for k in range(args.members):
            if args.only is not None and k not in args.only:
                continue
            path = args.out / f"member_{k}.pt"
            if path.exists() and not args.overwrite:
                log.write(json.dumps({"member": k, "event": "skipped", "reason": f"{path.name} exists"}) + "\n")
                continue
            ckpt = train_member(k, pool, eval_items, spec, args, log, progress, names)
            tmp = path.with_name(path.name + ".tmp")
            torch.save(ckpt, tmp)
            tmp.replace(path)  # atomic: a killed run never leaves half a checkpoint that resume would skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
