"""Recordings: the one data format of slipd (simulator output, recorder dumps, replay input).

On disk a recording is an ``.npz`` (see ``design.md`` section 3), a Contactile SDK CSV log, so
that recordings made with Contactile's own tools replay through the same code, or an ``.mcap`` file
(``slipd.recording_mcap``: the same arrays on channels that Foxglove opens).

Arrays (N samples, 9 pillars in SDK order):
    t_us            [N] int64        sample time, microseconds
    force           [N, 9, 3] f32    fx, fy, fz (N); [N, S, 9, 3] for S sensor arrays (two fingers)
    disp            [N, 9, 3] f32    dx, dy, dz (mm); [N, S, 9, 3] likewise
    slip            [N, 9] bool      optional truth: pillar tip sliding
    label           [N] uint8        optional truth: 1 = incipient slip
    object_motion   [N, 3] f32       optional truth: object motion relative to the finger (mm, mm, deg)
    friction_est    [N] f32          optional: the PapillArray controller's own friction estimate (its type-6
                                     block; the SDK log's ``S0_FrictionEst``), NaN where it reported none (the
                                     SDK's -1); [N, S] with S sensor arrays
    meta            dict             scene, seed, sensor, effects, kind ("slip" / "stop"), events (seconds)
"""

from __future__ import annotations

import csv
import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slipd.geometry import N_PILLARS, PILLAR_XY_MM
from slipd.recording_mcap import McapRecordingError, read_arrays

_AXES = ("X", "Y", "Z")
MAX_SENSORS = 8
"""Sensor arrays one recording may hold (the PTSCOM frame's limit)."""


class RecordingError(ValueError):
    """A recording file is missing, malformed, or inconsistent; the message names the file."""


@dataclass
class Recording:
    """One sensor stream with optional simulator truth. See the module docstring for shapes."""

    t_us: np.ndarray
    force: np.ndarray
    disp: np.ndarray
    slip: np.ndarray | None = None
    label: np.ndarray | None = None
    object_motion: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    friction_est: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Every message names the array at fault; the readers prefix the file.
        self.t_us = _array("t_us", self.t_us, np.int64)
        self.force = _array("force", self.force, np.float32)
        self.disp = _array("disp", self.disp, np.float32)
        if self.t_us.ndim != 1:
            raise RecordingError(f"t_us: shape {self.t_us.shape}, expected [N]")
        n = len(self.t_us)
        for name in ("force", "disp"):
            shape = getattr(self, name).shape
            several = len(shape) == 4 and 2 <= shape[1] <= MAX_SENSORS and shape[2:] == (N_PILLARS, 3)
            if shape != (n, N_PILLARS, 3) and not (several and shape[0] == n):
                alt = f" or [{n}, S, {N_PILLARS}, 3] for S = 2..{MAX_SENSORS} sensors" if len(shape) == 4 else ""
                raise RecordingError(f"{name}: shape {shape}, expected [{n}, {N_PILLARS}, 3]{alt} (N from t_us)")
        if self.force.shape != self.disp.shape:
            raise RecordingError(f"disp: shape {self.disp.shape} differs from force {self.force.shape}")
        if self.slip is not None:
            self.slip = _array("slip", self.slip, bool)
            if self.slip.shape != (n, N_PILLARS):
                raise RecordingError(f"slip: shape {self.slip.shape}, expected [{n}, {N_PILLARS}]")
        if self.label is not None:
            self.label = _array("label", self.label, np.uint8)
            if self.label.shape != (n,):
                raise RecordingError(f"label: shape {self.label.shape}, expected [{n}]")
        if self.object_motion is not None:
            self.object_motion = _array("object_motion", self.object_motion, np.float32)
            if self.object_motion.shape != (n, 3):
                raise RecordingError(f"object_motion: shape {self.object_motion.shape}, expected [{n}, 3]")
        if self.friction_est is not None:
            self.friction_est = _array("friction_est", self.friction_est, np.float32)
            want = self.force.shape[:-2]
            if self.friction_est.shape != want:
                raise RecordingError(f"friction_est: shape {self.friction_est.shape}, expected {list(want)}")

    def __len__(self) -> int:
        return len(self.t_us)

    @property
    def sensors(self) -> int:
        """Sensor arrays in the recording (1, or S of a [N, S, 9, 3] recording)."""
        return 1 if self.force.ndim == 3 else int(self.force.shape[1])

    def sensor(self, s: int) -> Recording:
        """Sensor ``s`` alone as a one-sensor recording (evaluation per finger); truth and meta are shared."""
        if not 0 <= s < self.sensors:
            raise IndexError(f"sensor {s} of a {self.sensors}-sensor recording")
        if self.sensors == 1:
            return self
        return Recording(self.t_us, self.force[:, s], self.disp[:, s], self.slip, self.label, self.object_motion,
                         {**self.meta, "sensor": s},
                         None if self.friction_est is None else self.friction_est[:, s])

    @property
    def rate_hz(self) -> float:
        """Nominal sample rate from the median sample spacing (1 kHz, the sensor's, where that says nothing: fewer
        than two samples, or timestamps that mostly repeat, which ``check_times`` accepts)."""
        if len(self.t_us) < 2:
            return 1000.0
        step = float(np.median(np.diff(self.t_us)))
        return 1e6 / step if step > 0 else 1000.0

    @property
    def events(self) -> dict[str, float]:
        """Named event times in seconds from the first sample (motion_start, onset, gross_slip, ...)."""
        return dict(self.meta.get("events", {}))

    def onset_index(self) -> int | None:
        """First sample labelled incipient slip, or None."""
        if self.label is None or not self.label.any():
            return None
        return int(np.argmax(self.label > 0))

    # ------------------------------------------------------------------ npz
    def save(self, path: str | Path) -> Path:
        """Write the recording as a compressed ``.npz`` atomically (temporary file + rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, Any] = {"t_us": self.t_us, "force": self.force, "disp": self.disp}
        for name in ("slip", "label", "object_motion", "friction_est"):
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        arrays["meta"] = np.array(json.dumps(self.meta, sort_keys=True))
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        """Read an ``.npz`` recording, an SDK CSV log or an ``.mcap`` recording (by extension).

        A broken file raises ``RecordingError`` with one line naming the file and the part at fault
        (``rec.npz: meta: not JSON: ...``, ``log.csv: T_us: goes backwards at sample 12 ...``).
        """
        path = Path(path)
        if path.suffix.lower() == ".csv":
            return read_sdk_csv(path)
        if path.suffix.lower() == ".mcap":
            return read_mcap(path)
        return read_npz(path)


# ---------------------------------------------------------------------- checks shared by the readers
_ARRAYS = ("t_us", "force", "disp", "slip", "label", "object_motion", "friction_est")
# Local file header, or the end-of-directory record that an archive with no members starts with.
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _array(name: str, value: Any, dtype: Any) -> np.ndarray:
    """``value`` as ``dtype``; refuses what would convert silently into garbage (NaN times, text)."""
    try:
        raw = np.asarray(value)
        if raw.dtype.kind not in "biuf":
            raise RecordingError(f"{name}: not numbers (dtype {raw.dtype})")
        if raw.dtype.kind == "f" and np.dtype(dtype).kind in "iub" and not np.isfinite(raw).all():
            bad = int(np.argmin(np.isfinite(raw).reshape(len(raw), -1).all(1))) if raw.ndim else 0
            raise RecordingError(f"{name}: not a finite number at sample {bad}")
        return raw.astype(dtype, copy=False)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, RecordingError):
            raise
        raise RecordingError(f"{name}: not numbers ({_one_line(exc)})") from None


def check_times(t_us: np.ndarray, name: str = "t_us") -> None:
    """Refuse timestamps that go backwards: replayed, they would feed the detector a reordered stream."""
    if len(t_us) < 2:
        return
    back = np.flatnonzero(np.diff(t_us) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise RecordingError(
            f"{name}: goes backwards at sample {i} ({int(t_us[i - 1])} -> {int(t_us[i])} us)"
            + (f"; {len(back)} such samples" if len(back) > 1 else "")
        )


def _parse_meta(text: str) -> dict[str, Any]:
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RecordingError(f"meta: not JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise RecordingError(f"meta: not a JSON object (got {type(meta).__name__})")
    return meta


def read_npz(path: str | Path) -> Recording:
    """Read an ``.npz`` recording; ``RecordingError`` names the file and the part at fault."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if head not in _ZIP_MAGIC:
        # np.load would try the file as a bare .npy, then as a pickle, and report that instead.
        what = "empty file" if not head else f"starts with {head!r}"
        raise RecordingError(f"{path}: not an .npz recording (not a zip archive: {what})")
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: not an .npz recording (broken zip archive: {_one_line(exc)})") from None
    try:
        with npz:
            missing = [k for k in ("t_us", "force", "disp") if k not in npz.files]
            if missing:
                raise RecordingError(f"missing array(s) {', '.join(missing)} (has: {', '.join(npz.files) or 'none'})")
            arrays: dict[str, Any] = {}
            for name in (*_ARRAYS, "meta"):
                if name in npz.files:
                    try:
                        arrays[name] = npz[name]
                    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError, KeyError) as exc:
                        raise RecordingError(f"{name}: cannot read ({_one_line(exc)})") from None
        meta: dict[str, Any] = {}
        if "meta" in arrays:
            m = arrays.pop("meta")
            if m.shape != () or m.dtype.kind not in "US":
                raise RecordingError(f"meta: not a JSON string (dtype {m.dtype}, shape {m.shape})")
            meta = _parse_meta(str(m))
        rec = Recording(**arrays, meta=meta)
        check_times(rec.t_us)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    return rec


# ---------------------------------------------------------------------- SDK CSV
def sdk_csv_columns(sensors: int = 1) -> list[str]:
    """Column names of the Contactile SDK log layout: ``T_us``, then each sensor's block (S0, S1, ...)."""
    cols = ["T_us"]
    for s in range(sensors):
        cols += _sensor_columns(f"S{s}")
    return cols


def _pillar_columns(sn: str) -> list[str]:
    """A sensor's pillar displacement and force columns, the ones a recording needs (pillar-major, D then F)."""
    return [f"{sn}_P{p}_{q}{a}" for p in range(N_PILLARS) for q in "DF" for a in _AXES]


def _sensor_columns(sn: str) -> list[str]:
    cols = _pillar_columns(sn)
    cols += [f"{sn}_GG_F{a}" for a in _AXES] + [f"{sn}_GG_T{a}" for a in _AXES]
    cols += [f"{sn}_isSDActive", f"{sn}_isRefLoad"]
    for p in range(N_PILLARS):
        cols += [f"{sn}_P{p}_isInContact", f"{sn}_P{p}_slipState"]
    cols += [f"{sn}_FrictionEst"]
    return cols


_SENSOR_COLS = len(_sensor_columns("S0"))


# Our own extra columns carry simulator truth so a CSV round trip loses nothing.
_TRUTH_SLIP = [f"SLIPD_P{p}_slip" for p in range(N_PILLARS)]
_TRUTH_REST = ["SLIPD_label", "SLIPD_obj_x_mm", "SLIPD_obj_y_mm", "SLIPD_obj_rot_deg"]


def global_wrench(force: np.ndarray) -> np.ndarray:
    """[N, 6] global force (N) and torque (N mm) about the sensor centre, as the SDK reports it."""
    f = force.astype(np.float64)
    x = PILLAR_XY_MM[:, 0]
    y = PILLAR_XY_MM[:, 1]
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    tx = (y * fz).sum(-1)
    ty = (-x * fz).sum(-1)
    tz = (x * fy - y * fx).sum(-1)
    return np.stack([fx.sum(-1), fy.sum(-1), fz.sum(-1), tx, ty, tz], axis=-1)


def write_sdk_csv(rec: Recording, path: str | Path, contact_threshold_n: float = 0.5) -> Path:
    """Write ``rec`` in the Contactile SDK CSV log layout (plus SLIPD_* truth columns when present).

    Written atomically: a temporary file renamed into place, so a crash never leaves half a log.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(rec)
    ns = rec.sensors
    cols = sdk_csv_columns(ns)
    block = np.empty((n, len(cols)), dtype=np.float64)
    block[:, 0] = rec.t_us
    float32_cols: set[int] = set()
    for s in range(ns):
        one = rec.sensor(s)
        b = block[:, 1 + s * _SENSOR_COLS : 1 + (s + 1) * _SENSOR_COLS]
        float32_cols.update(range(1 + s * _SENSOR_COLS, 1 + s * _SENSOR_COLS + 54))
        b[:, 0:54] = np.concatenate([one.disp, one.force], axis=2).reshape(n, N_PILLARS * 6)
        b[:, 54:60] = global_wrench(one.force)
        b[:, 60] = 0
        b[:, 61] = 0
        states = np.zeros((n, N_PILLARS, 2))
        states[:, :, 0] = one.force[:, :, 2] > contact_threshold_n
        b[:, 62 : 62 + 18] = states.reshape(n, 18)
        b[:, 80] = -1 if one.friction_est is None else np.nan_to_num(one.friction_est, nan=-1.0)
    extra_cols: list[str] = []
    extra: list[np.ndarray] = []
    if rec.slip is not None:
        extra_cols += _TRUTH_SLIP
        extra.append(rec.slip.astype(np.float64))
    if rec.label is not None:
        extra_cols.append(_TRUTH_REST[0])
        extra.append(rec.label[:, None].astype(np.float64))
    if rec.object_motion is not None:
        extra_cols += _TRUTH_REST[1:]
        extra.append(rec.object_motion.astype(np.float64))
    if extra:
        block = np.concatenate([block, *extra], axis=1)
        cols = cols + extra_cols
    tmp = path.with_name(path.name + ".tmp")
    int_cols = {i for i, c in enumerate(cols) if c == "T_us" or "_is" in c[:4] or c.endswith(
        ("isInContact", "slipState", "_slip", "_label", "isSDActive", "isRefLoad"))}
    with open(tmp, "w", newline="") as fh:
        if rec.meta:
            # A comment line keeps scene metadata; the SDK reader of slipd skips lines starting with '#'.
            fh.write("# slipd-meta " + json.dumps(rec.meta, sort_keys=True) + "\n")
        w = csv.writer(fh)
        w.writerow(cols)
        for row in block:
            # repr of float32 values round-trips exactly through float().
            w.writerow(
                [str(int(v)) if i in int_cols else repr(float(np.float32(v))) if i in float32_cols else repr(float(v))
                 for i, v in enumerate(row)]
            )
    tmp.replace(path)
    return path


def read_sdk_csv(path: str | Path) -> Recording:
    """Read a Contactile SDK CSV log: sensor S0, and S1, S2, ... when their columns are there (a [N, S, 9, 3]
    recording). Unknown columns are ignored.

    Raises RecordingError with one line naming the file and the part at fault: a missing column, the
    line and column of a value that is not a number, a row of the wrong length, timestamps that go
    backwards, a ``# slipd-meta`` line that is not JSON.
    """
    path = Path(path)
    meta: dict[str, Any] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: a file re-saved by a spreadsheet has a BOM
            lines = fh.readlines()
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise RecordingError(f"{path}: not a CSV text file (byte {exc.start} is not UTF-8)") from None
    body: list[tuple[int, str]] = []  # (1-based file line, text)
    for lineno, line in enumerate(lines, 1):
        if line.startswith("# slipd-meta "):
            try:
                meta = _parse_meta(line[len("# slipd-meta ") :])
            except RecordingError as exc:
                raise RecordingError(f"{path}:{lineno}: {exc}") from None
        elif not line.startswith("#") and line.strip():
            body.append((lineno, line))
    if not body:
        raise RecordingError(f"{path}: empty CSV (no header)")
    try:
        header = [h.strip() for h in next(csv.reader([body[0][1]]))]
        rows = [(lineno, r) for lineno, r in zip((b[0] for b in body[1:]), csv.reader(b[1] for b in body[1:]))
                if r]
    except csv.Error as exc:
        raise RecordingError(f"{path}: not CSV ({_one_line(exc)})") from None
    index = {name: i for i, name in enumerate(header)}
    needed = ["T_us", *_pillar_columns("S0")]
    missing = [c for c in needed if c not in index]
    if missing:
        raise RecordingError(f"{path}: missing SDK column(s) {missing[:4]}{'...' if len(missing) > 4 else ''}")
    data = np.empty((len(rows), len(header)), dtype=np.float64)
    for k, (lineno, r) in enumerate(rows):
        if len(r) != len(header):
            raise RecordingError(f"{path}:{lineno}: {len(r)} values, but the header has {len(header)} columns")
        for j, v in enumerate(r):
            try:
                data[k, j] = float(v) if v.strip() else np.nan
            except ValueError:
                raise RecordingError(f"{path}:{lineno}: {header[j]}: not a number ({v[:40]!r})") from None

    def col(name: str) -> np.ndarray:
        return data[:, index[name]]

    t = col("T_us")
    if not np.isfinite(t).all():
        k = int(np.argmin(np.isfinite(t)))
        raise RecordingError(f"{path}:{rows[k][0]}: T_us: missing or not finite (sample {k})")
    ns = 1
    while ns < MAX_SENSORS and all(c in index for c in _pillar_columns(f"S{ns}")):
        ns += 1
    partial = _pillar_columns(f"S{ns}") if ns < MAX_SENSORS else []
    if any(c in index for c in partial):
        # A finger's block with columns missing: reading the file as one finger fewer would drop that finger silently.
        gone = [c for c in partial if c not in index]
        raise RecordingError(f"{path}: sensor S{ns} has {len(partial) - len(gone)} of its {len(partial)} columns; "
                             f"missing {gone[:4]}{'...' if len(gone) > 4 else ''}")

    def values(q: str) -> np.ndarray:
        per = [np.stack([np.stack([col(f"S{s}_P{p}_{q}{a}") for a in _AXES], -1) for p in range(N_PILLARS)], 1)
               for s in range(ns)]
        return per[0] if ns == 1 else np.stack(per, 1)

    force, disp = values("F"), values("D")
    slip = None
    if all(c in index for c in _TRUTH_SLIP):
        slip = np.stack([col(c) for c in _TRUTH_SLIP], 1) > 0.5
    label = None
    if "SLIPD_label" in index:
        label = np.nan_to_num(col("SLIPD_label")).astype(np.uint8)
    motion = None
    if all(c in index for c in _TRUTH_REST[1:]):
        motion = np.stack([col(c) for c in _TRUTH_REST[1:]], 1)
    friction_est = None
    if all(f"S{s}_FrictionEst" in index for s in range(ns)):
        # The controller writes -1 where it has no estimate.
        est = np.stack([col(f"S{s}_FrictionEst") for s in range(ns)], 1)
        est[~(est >= 0)] = np.nan
        if np.isfinite(est).any():
            friction_est = est[:, 0] if ns == 1 else est
    try:
        rec = Recording(
            t_us=t.astype(np.int64), force=force, disp=disp, slip=slip, label=label, object_motion=motion, meta=meta,
            friction_est=friction_est,
        )
        check_times(rec.t_us, "T_us")
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    return rec


def read_mcap(path: str | Path) -> Recording:
    """Read an ``.mcap`` recording (``slipd.recording_mcap``); ``RecordingError`` names the file and the part at
    fault."""
    path = Path(path)
    try:
        rec = Recording(**read_arrays(path))
        check_times(rec.t_us)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (RecordingError, McapRecordingError) as exc:
        raise RecordingError(f"{path}: {exc}") from None
    return rec


def list_recordings(folder: str | Path) -> list[Path]:
    """All ``.npz``, ``.csv`` and ``.mcap`` recordings below ``folder``, sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in SUFFIXES and p.is_file())


SUFFIXES = (".npz", ".csv", ".mcap")
"""The file name endings of recordings, one per format."""
