"""The slip-detection ensemble at run time: one onnxruntime session of the fused ONNX graph.

``Ensemble.load(manifest_path)`` validates the manifest and its model (``slipd.detect.manifest``), opens a
session tuned for a latency-bound 25 Hz step on a shared machine (one intra-op thread, no spinning,
sequential execution, full graph optimisation), checks the session's I/O against the manifest and
runs a warm-up step before it returns, so the first real decision does not pay for lazy
initialisation.

Hidden states are kept per *stream* (an integer key: one sensor, one replayed recording, ...).
``step(window, stream)`` feeds one window (``[T*C]``, or ``[B, T*C]`` for B parallel sequences in one
stream) and carries that stream's GRU state to the next call. Each stream owns preallocated buffers
(input, two hidden-state buffers used in turn, outputs) bound once to the session with IOBinding, so a
step allocates nothing but the small result it returns.

Non-finite policy (the second line of defence; ``slipd.detect.features`` already replaces non-finite samples).
``step`` does not raise for these; it returns an invalid ``StepResult`` (``valid`` False, ``p_slip`` NaN,
``status`` saying why) so a 25 Hz loop needs no try/except, and a NaN used by mistake is refused by
``Decision.update``:
  * ``status == "nonfinite_input"``: the window contains NaN or +-Inf; the stream's state is untouched, so the
    next good window continues the sequence (a stream under way checks its window with the outputs, in one pass after
    the call, and drops that call's outputs; a new stream is made for a finite window only);
  * ``status == "nonfinite_output"``: an output or the next hidden state came back non-finite; it is not
    stored: the stream is reset to zeros (the model's initial state).
Both are counted (``refused_inputs``, ``nonfinite_outputs``). ``step_batch`` (offline evaluation) raises
``NonFiniteInput`` / ``NonFiniteOutput`` instead: there a silent gap would bias the figures.
An ``Ensemble`` is not thread-safe: one owner calls ``step``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slipd.detect.features import FeatureSpec
from slipd.detect.manifest import Manifest, check_session_io, load_manifest, onnx_path_of, open_session
from slipd.detect.ort import onnxruntime as ort


class StepError(Exception):
    """A step that produced no decision. See the module docstring for the policy."""


class NonFiniteInput(StepError, ValueError):
    """The window contains NaN or +-Inf; it was refused and the stream's state is unchanged."""


class NonFiniteOutput(StepError, RuntimeError):
    """The model produced a non-finite output or state; the stream was reset to its initial state."""


STATUS_OK, STATUS_NONFINITE_INPUT, STATUS_NONFINITE_OUTPUT = "ok", "nonfinite_input", "nonfinite_output"


@dataclass(frozen=True)
class StepResult:
    """One decision step. For a 1-D window ``p_slip`` is a float and ``p_members`` is [Z];
    for a [B, T*C] window they are [B] and [Z, B]. When ``valid`` is False they are NaN and
    ``status`` says why (see the module docstring)."""

    p_slip: float | np.ndarray
    p_members: np.ndarray
    status: str = STATUS_OK
    p_pillars: np.ndarray | None = None
    """P(slip) of each model pillar ([P], or [B, P]) where the graph has a per-pillar head, else None."""

    @property
    def valid(self) -> bool:
        """True when the step produced a decision."""
        return self.status == STATUS_OK


@dataclass(frozen=True)
class SequenceResult:
    """``step_batch`` output for one sequence of K windows: ``p_slip`` [K], ``p_members`` [Z, K]."""

    p_slip: np.ndarray
    p_members: np.ndarray
    p_pillars: np.ndarray | None = None
    """[K, P] where the graph has a per-pillar head."""


class _Stream:
    """Buffers and bindings of one stream: h ping-pongs between two buffers, so a bad h_next never
    overwrites the good state."""

    def __init__(self, session: ort.InferenceSession, batch: int, z: int, d: int, h: int, pillars: int = 0) -> None:
        self.batch = batch
        # The input, everything the session writes and both states side by side in one buffer: a step checks its
        # window and its outputs for non-finite values in one call after the run (``checked``; the state being replaced
        # is finite already: only finite states are kept), ``outputs`` without the window.
        sizes = (batch * d, batch, z * batch, z * batch * h, z * batch * h, batch * pillars)
        self.checked = np.zeros(sum(sizes), np.float32)
        cuts = np.cumsum(sizes)[:-1]
        x, p_slip, p_members, h0, h1, p_pillars = np.split(self.checked, cuts)
        self.x = x.reshape(batch, d)
        self.outputs = self.checked[batch * d :]
        self.p_slip = p_slip
        self.p_members = p_members.reshape(z, batch)
        self.h = [h0.reshape(z, batch, h), h1.reshape(z, batch, h)]
        self.p_pillars = p_pillars.reshape(batch, pillars) if pillars else None
        self.cur = 0  # index of the buffer holding the current state
        x_v = ort.OrtValue.ortvalue_from_numpy(self.x)
        h_v = [ort.OrtValue.ortvalue_from_numpy(a) for a in self.h]
        p_v = ort.OrtValue.ortvalue_from_numpy(self.p_slip)
        pm_v = ort.OrtValue.ortvalue_from_numpy(self.p_members)
        self.bindings = []
        for src in (0, 1):
            b = session.io_binding()
            b.bind_ortvalue_input("window", x_v)
            b.bind_ortvalue_input("h", h_v[src])
            b.bind_ortvalue_output("p_slip", p_v)
            b.bind_ortvalue_output("p_members", pm_v)
            b.bind_ortvalue_output("h_next", h_v[1 - src])
            self.bindings.append(b)
        self._values: tuple[Any, ...] = (x_v, h_v, p_v, pm_v)  # keep the OrtValues (the shared memory) alive
        if self.p_pillars is not None:
            pp_v = ort.OrtValue.ortvalue_from_numpy(self.p_pillars)
            for b in self.bindings:
                b.bind_ortvalue_output("p_pillars", pp_v)
            self._values += (pp_v,)

    def reset(self) -> None:
        self.h[self.cur][:] = 0.0


def _all_finite(a: np.ndarray) -> bool:
    """No NaN or +-Inf in ``a``: no zero byte among its flags (a byte search; ndarray.all goes through a Python wrapper,
    and a finite sum needs a reduction, both costing more on the hot path)."""
    return 0 not in np.isfinite(a).tobytes()


def session_options(threads: int = 1) -> ort.SessionOptions:
    """Options for a latency-bound step on a shared CPU: no busy-waiting threads, sequential graph."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Spinning threads would burn the shared cores between the 25 Hz steps.
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return so


class Ensemble:
    """The fused ensemble with per-stream GRU states. Create with ``Ensemble.load``."""

    def __init__(self, session: ort.InferenceSession, manifest: Manifest, manifest_path: Path) -> None:
        self._session = session
        self.manifest = manifest
        self.manifest_path = manifest_path
        self._spec = manifest.spec
        self._z, self._h, self._d = manifest.members, manifest.hidden, self._spec.input_size
        self._p = len(self._spec.pillars) if manifest.has_pillar_output else 0
        self.pillar_rows: np.ndarray | None = None
        """[B, P] per-pillar P(slip) of the latest ``step_rows`` (NaN in rows that did not step); None without a
        per-pillar head."""
        self._streams: dict[int, _Stream] = {}
        self.refused_inputs = 0
        """Windows refused because they held non-finite values (stream state untouched)."""
        self.nonfinite_outputs = 0
        """Steps whose output or state was non-finite (stream reset)."""

    @classmethod
    def load(
        cls, manifest_path: str | os.PathLike[str], threads: int = 1, expected_spec: FeatureSpec | None = None
    ) -> Ensemble:
        """Validate the manifest and model (``ModelError`` on any mismatch), open the session, warm up."""
        path = Path(manifest_path)
        manifest = load_manifest(path, expected_spec=expected_spec, check_graph=False)
        onnx_path = onnx_path_of(manifest, path)
        session = open_session(onnx_path, session_options(threads))
        check_session_io(manifest, session, onnx_path)
        ens = cls(session, manifest, path)
        ens._warm_up()
        return ens

    def _warm_up(self) -> None:
        # Two runs: the first triggers lazy allocations and kernel selection, the second reuses them.
        warm = _Stream(self._session, 1, self._z, self._d, self._h)
        for _ in range(2):
            self._session.run_with_iobinding(warm.bindings[0])

    @property
    def feature_spec(self) -> FeatureSpec:
        """The feature layout the model was trained on (from the manifest)."""
        return self._spec

    @property
    def members(self) -> int:
        """Ensemble size Z."""
        return self._z

    @property
    def hidden(self) -> int:
        """GRU hidden size H."""
        return self._h

    @property
    def threshold(self) -> float:
        """The manifest's decision threshold."""
        return self.manifest.threshold

    @property
    def streams(self) -> list[int]:
        """Streams that currently hold a state."""
        return sorted(self._streams)

    def hidden_state(self, stream: int = 0) -> np.ndarray:
        """A copy of a stream's GRU state [Z, B, H] (zeros for a stream never stepped)."""
        st = self._streams.get(stream)
        return np.zeros((self._z, 1, self._h), np.float32) if st is None else st.h[st.cur].copy()

    def reset(self, stream: int | None = None) -> None:
        """Forget the state of one stream (back to zeros), or of all streams with ``None``."""
        if stream is None:
            self._streams.clear()
        else:
            self._streams.pop(stream, None)

    def step(self, window: np.ndarray, stream: int = 0) -> StepResult:
        """Run one window through the ensemble, carrying ``stream``'s hidden state.

        A non-finite window or output gives an invalid result (see the module docstring); a window of the
        wrong size, or a batch size other than the stream's, raises ``ValueError``.
        """
        w = np.asarray(window)
        single = w.ndim == 1
        if single:
            w = w[None, :]
        if w.ndim != 2 or w.shape[1] != self._d:
            raise ValueError(f"window must be [{self._d}] or [B, {self._d}], got {np.shape(window)}")
        st = self._run(w, stream, w.shape[0])
        if isinstance(st, str):
            return self._invalid(w.shape[0], single, st)
        pp = st.p_pillars
        if single:
            return StepResult(float(st.p_slip[0]), st.p_members[:, 0].copy(),
                              p_pillars=None if pp is None else pp[0].copy())
        return StepResult(st.p_slip.copy(), st.p_members.copy(), p_pillars=None if pp is None else pp.copy())

    def step_one(self, window: np.ndarray, stream: int = 0) -> tuple[float, np.ndarray | None]:
        """``step`` on one window [T*C] without its result object (the detector's call, once per decision): the mean
        P(slip) and a copy of the per-pillar P(slip) [P] (None without a per-pillar head); NaN and None where the step
        made no decision (counted as in ``step``)."""
        w = np.asarray(window)
        if w.shape != (self._d,):
            raise ValueError(f"window must be [{self._d}], got {w.shape}")
        st = self._run(w, stream, 1)  # (the window as it is: the copy into the stream's [1, T*C] input broadcasts it)
        if isinstance(st, str):
            return math.nan, None
        pp = st.p_pillars
        return st.p_slip.item(0), None if pp is None else pp[0].copy()

    def _run(self, w: np.ndarray, stream: int, batch: int) -> _Stream | str:
        """One model call on ``w`` ([batch, T*C], or [T*C] for a batch of one) in ``stream``: the stream, its outputs
        in its buffers and its state advanced, or the status of a step that made no decision (see the module
        docstring)."""
        st = self._streams.get(stream)
        if st is None:
            if not _all_finite(w):  # (a stream is made for a finite window only)
                self.refused_inputs += 1
                return STATUS_NONFINITE_INPUT
            st = self._streams[stream] = _Stream(self._session, batch, self._z, self._d, self._h, self._p)
        elif st.batch != batch:
            raise ValueError(f"stream {stream} holds {st.batch} sequences, window has {batch}; reset it first")
        st.x[...] = w  # (np.copyto's copy, without its Python-level dispatcher)
        self._session.run_with_iobinding(st.bindings[st.cur])
        if not _all_finite(st.checked):  # the window, p_slip, p_members, h_next (and p_pillars) in one pass
            if not _all_finite(st.x):
                # Refused: the outputs of a non-finite window are dropped, and its state (the other buffer) stands.
                self.refused_inputs += 1
                return STATUS_NONFINITE_INPUT
            st.reset()
            self.nonfinite_outputs += 1
            return STATUS_NONFINITE_OUTPUT
        st.cur = 1 - st.cur
        return st

    def step_rows(
        self, windows: np.ndarray, stream: int, active: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One model call for B independent sequences kept side by side in ``stream`` (the sensors of a
        gripper: one row each), where not every row steps every time.

        ``windows`` [B, T*C]; only rows with ``active`` set and a finite window advance. The others keep
        their state and take no part in the call: while it runs they hold a copy of the first stepped
        row's window and state (the int8 graph quantises each tensor with one scale over the whole batch,
        so a stale or zero row would shift the others' values; a copy leaves the range as it is, and a
        single stepped row gets the values ``step`` gives it alone). A non-finite window is refused
        (state kept), a row whose output or next state is non-finite is reset to zeros, each counted as
        in ``step``. Returns copies of (p_slip [B], p_members [Z, B], valid [B]); rows that did not step
        read NaN.
        """
        w = np.asarray(windows)
        act = np.asarray(active, bool)
        if w.ndim != 2 or w.shape[1] != self._d or act.shape != (len(w),):
            raise ValueError(f"windows must be [B, {self._d}] with active [B], got {w.shape} and {act.shape}")
        b = len(w)
        st = self._streams.get(stream)
        if st is not None and st.batch != b:
            raise ValueError(f"stream {stream} holds {st.batch} sequences, windows has {b}; reset it first")
        common = False
        if st is not None and 0 not in act.tobytes():  # (every flag set: a byte search, cheaper than ndarray.all)
            # Every row steps (the fingers of a grasp, decision after decision): no row to keep aside, and when the
            # windows and every output are finite (one check after the call), every row is valid.
            st.x[...] = w  # (np.copyto's copy, without its Python-level dispatcher)
            self._session.run_with_iobinding(st.bindings[st.cur])
            if _all_finite(st.checked):
                st.cur = 1 - st.cur
                if st.p_pillars is not None:
                    self.pillar_rows = st.p_pillars.copy()
                return st.p_slip.copy(), st.p_members.copy(), act.copy()
            # Something non-finite: an output (checked below), or a window: then this call's outputs are dropped
            # (every state stands) and the call is made again below without that row.
            common = _all_finite(st.x)
        if common and st is not None:
            run = act
            kept = None
            h_next = st.h[1 - st.cur]
            p = np.full(b, np.nan, np.float32)
            pm = np.full((self._z, b), np.nan, np.float32)
        else:
            finite = np.isfinite(w).all(axis=1)
            run = act & finite
            self.refused_inputs += int(np.count_nonzero(act & ~finite))
            p = np.full(b, np.nan, np.float32)
            pm = np.full((self._z, b), np.nan, np.float32)
            if not run.any():
                return p, pm, run
            if st is None:
                st = self._streams[stream] = _Stream(self._session, b, self._z, self._d, self._h, self._p)
            idle = ~run
            h_cur, h_next = st.h[st.cur], st.h[1 - st.cur]
            kept = h_cur[:, idle].copy() if idle.any() else None
            np.copyto(st.x, w, casting="same_kind")
            if kept is not None:
                first = int(np.argmax(run))
                st.x[idle] = st.x[first]
                h_cur[:, idle] = h_cur[:, first : first + 1]
            self._session.run_with_iobinding(st.bindings[st.cur])
        ok = run & np.isfinite(st.p_slip) & np.isfinite(st.p_members).all(axis=0) & np.isfinite(h_next).all(axis=(0, 2))
        bad = run & ~ok
        if bad.any():
            h_next[:, bad] = 0.0
            self.nonfinite_outputs += int(np.count_nonzero(bad))
        if kept is not None:
            h_next[:, ~run] = kept
        st.cur = 1 - st.cur
        p[ok] = st.p_slip[ok]
        pm[:, ok] = st.p_members[:, ok]
        if st.p_pillars is not None:
            self.pillar_rows = np.full(st.p_pillars.shape, np.nan, np.float32)
            self.pillar_rows[ok] = st.p_pillars[ok]
        return p, pm, ok

    def reset_row(self, row: int) -> None:
        """Forget one row's state (one sensor of ``step_rows``) in every stream; the other rows keep theirs."""
        for st in self._streams.values():
            if row < st.batch:
                st.h[st.cur][:, row] = 0.0

    def _invalid(self, batch: int, single: bool, status: str) -> StepResult:
        if single:
            return StepResult(float("nan"), np.full(self._z, np.nan, np.float32), status)
        return StepResult(np.full(batch, np.nan, np.float32), np.full((self._z, batch), np.nan, np.float32), status)

    def step_batch(self, sequences: Sequence[np.ndarray] | np.ndarray) -> list[SequenceResult]:
        """Run many independent sequences (each [K_i, T*C], from zero state) in batched calls.

        For evaluation: all sequences advance together, one window per call, and a sequence leaves
        the batch when it ends. Stream states are not touched. Non-finite windows raise
        ``NonFiniteInput`` naming the sequence and window.
        """
        seqs = [np.asarray(s, dtype=np.float32) for s in sequences]
        for i, s in enumerate(seqs):
            if s.ndim != 2 or s.shape[1] != self._d:
                raise ValueError(f"sequence {i} must be [K, {self._d}], got {s.shape}")
            bad = ~np.isfinite(s)
            if bad.any():
                raise NonFiniteInput(f"sequence {i}, window {int(np.argwhere(bad)[0, 0])}: non-finite values")
        lengths = np.array([len(s) for s in seqs], dtype=np.int64)
        order = np.argsort(-lengths, kind="stable")  # longest first: active sequences are a prefix
        results = [(np.zeros(n, np.float32), np.zeros((self._z, n), np.float32)) for n in lengths]
        pillars = [np.zeros((n, self._p), np.float32) for n in lengths] if self._p else None
        h = np.zeros((self._z, len(seqs), self._h), np.float32)
        x = np.zeros((len(seqs), self._d), np.float32)
        sorted_len = lengths[order]
        for k in range(int(lengths.max(initial=0))):
            active = int((sorted_len > k).sum())
            for j in range(active):
                x[j] = seqs[order[j]][k]
            outs = self._session.run(None, {"window": x[:active], "h": np.ascontiguousarray(h[:, :active])})
            p, pm, h_next = outs[:3]
            if not (np.isfinite(pm).all() and np.isfinite(h_next).all()):
                raise NonFiniteOutput(f"window {k}: model output or state is non-finite")
            h[:, :active] = h_next
            for j in range(active):
                res = results[order[j]]
                res[0][k] = p[j]
                res[1][:, k] = pm[:, j]
                if pillars is not None:
                    pillars[order[j]][k] = outs[3][j]
        if pillars is None:
            return [SequenceResult(p, pm) for p, pm in results]
        return [SequenceResult(p, pm, pp) for (p, pm), pp in zip(results, pillars)]
