"""Recordings: the one data format of slipd (simulator output, recorder dumps, replay input).

On disk a recording is an ``.npz`` (see ``design.md`` section 3) or a Contactile SDK CSV log, so
that recordings made with Contactile's own tools replay through the same code.

Arrays (N samples, 9 pillars in SDK order):
    t_us            [N] int64        sample time, microseconds
    force           [N, 9, 3] f32    fx, fy, fz (N)
    disp            [N, 9, 3] f32    dx, dy, dz (mm)
    slip            [N, 9] bool      optional truth: pillar tip sliding
    label           [N] uint8        optional truth: 1 = incipient slip
    object_motion   [N, 3] f32       optional truth: object motion relative to the finger (mm, mm, deg)
    meta            dict             scene, seed, sensor, effects, kind ("slip" / "stop"), events (seconds)
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slipd.geometry import N_PILLARS, PILLAR_XY_MM

_AXES = ("X", "Y", "Z")


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

    def __post_init__(self) -> None:
        self.t_us = np.asarray(self.t_us, dtype=np.int64)
        self.force = np.asarray(self.force, dtype=np.float32)
        self.disp = np.asarray(self.disp, dtype=np.float32)
        n = len(self.t_us)
        if self.force.shape != (n, N_PILLARS, 3) or self.disp.shape != (n, N_PILLARS, 3):
            raise RecordingError(
                f"force/disp must be [{n}, 9, 3]; got {self.force.shape} and {self.disp.shape}"
            )
        if self.slip is not None:
            self.slip = np.asarray(self.slip, dtype=bool)
            if self.slip.shape != (n, N_PILLARS):
                raise RecordingError(f"slip must be [{n}, 9]; got {self.slip.shape}")
        if self.label is not None:
            self.label = np.asarray(self.label, dtype=np.uint8)
            if self.label.shape != (n,):
                raise RecordingError(f"label must be [{n}]; got {self.label.shape}")
        if self.object_motion is not None:
            self.object_motion = np.asarray(self.object_motion, dtype=np.float32)
            if self.object_motion.shape != (n, 3):
                raise RecordingError(f"object_motion must be [{n}, 3]; got {self.object_motion.shape}")

    def __len__(self) -> int:
        return len(self.t_us)

    @property
    def rate_hz(self) -> float:
        """Nominal sample rate from the median sample spacing."""
        if len(self.t_us) < 2:
            return 1000.0
        return 1e6 / float(np.median(np.diff(self.t_us)))

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
        arrays: dict[str, np.ndarray] = {"t_us": self.t_us, "force": self.force, "disp": self.disp}
        for name in ("slip", "label", "object_motion"):
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
        """Read an ``.npz`` recording or an SDK CSV log (by extension)."""
        path = Path(path)
        if path.suffix.lower() == ".csv":
            return read_sdk_csv(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [k for k in ("t_us", "force", "disp") if k not in data]
                if missing:
                    raise RecordingError(f"{path}: missing arrays {missing}")
                meta = json.loads(str(data["meta"])) if "meta" in data else {}
                return cls(
                    t_us=data["t_us"],
                    force=data["force"],
                    disp=data["disp"],
                    slip=data.get("slip", None),
                    label=data.get("label", None),
                    object_motion=data.get("object_motion", None),
                    meta=meta,
                )
        except RecordingError as exc:
            if str(path) in str(exc):
                raise
            raise RecordingError(f"{path}: {exc}") from None
        except (OSError, ValueError, KeyError) as exc:
            raise RecordingError(f"{path}: not a readable recording ({exc})") from exc


# ---------------------------------------------------------------------- SDK CSV
def sdk_csv_columns() -> list[str]:
    """Column names of the Contactile SDK log layout for one sensor (S0)."""
    cols = ["T_us"]
    for p in range(N_PILLARS):
        cols += [f"S0_P{p}_D{a}" for a in _AXES] + [f"S0_P{p}_F{a}" for a in _AXES]
    cols += [f"S0_GG_F{a}" for a in _AXES] + [f"S0_GG_T{a}" for a in _AXES]
    cols += ["S0_isSDActive", "S0_isRefLoad"]
    for p in range(N_PILLARS):
        cols += [f"S0_P{p}_isInContact", f"S0_P{p}_slipState"]
    cols += ["S0_FrictionEst"]
    return cols


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
    cols = sdk_csv_columns()
    block = np.empty((n, len(cols)), dtype=np.float64)
    block[:, 0] = rec.t_us
    per_pillar = np.concatenate([rec.disp, rec.force], axis=2).reshape(n, N_PILLARS * 6)
    block[:, 1 : 1 + 54] = per_pillar
    block[:, 55:61] = global_wrench(rec.force)
    block[:, 61] = 0
    block[:, 62] = 0
    contact = rec.force[:, :, 2] > contact_threshold_n
    states = block[:, 63 : 63 + 18].reshape(n, N_PILLARS, 2)
    states[:, :, 0] = contact
    states[:, :, 1] = 0
    block[:, 63 : 63 + 18] = states.reshape(n, 18)
    block[:, 81] = -1
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
    int_cols = {i for i, c in enumerate(cols) if c == "T_us" or c.startswith("S0_is") or c.endswith(
        ("isInContact", "slipState", "_slip", "_label"))}
    with open(tmp, "w", newline="") as fh:
        if rec.meta:
            # A comment line keeps scene metadata; the SDK reader of slipd skips lines starting with '#'.
            fh.write("# slipd-meta " + json.dumps(rec.meta, sort_keys=True) + "\n")
        w = csv.writer(fh)
        w.writerow(cols)
        for row in block:
            # repr of float32 values round-trips exactly through float().
            w.writerow(
                [str(int(v)) if i in int_cols else repr(float(np.float32(v))) if 1 <= i < 55 else repr(float(v))
                 for i, v in enumerate(row)]
            )
    tmp.replace(path)
    return path


def read_sdk_csv(path: str | Path) -> Recording:
    """Read a Contactile SDK CSV log (one sensor, S0). Unknown columns are ignored.

    Raises RecordingError naming the file and the missing column when the layout does not match.
    """
    path = Path(path)
    meta: dict[str, Any] = {}
    try:
        with open(path, newline="") as fh:
            lines = fh.readlines()
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc})") from exc
    body = []
    for line in lines:
        if line.startswith("# slipd-meta "):
            meta = json.loads(line[len("# slipd-meta ") :])
        elif not line.startswith("#") and line.strip():
            body.append(line)
    if not body:
        raise RecordingError(f"{path}: empty CSV")
    reader = csv.reader(body)
    header = [h.strip() for h in next(reader)]
    index = {name: i for i, name in enumerate(header)}
    needed = ["T_us"] + [f"S0_P{p}_{q}{a}" for p in range(N_PILLARS) for q in "DF" for a in _AXES]
    missing = [c for c in needed if c not in index]
    if missing:
        raise RecordingError(f"{path}: missing SDK column(s) {missing[:4]}{'...' if len(missing) > 4 else ''}")
    rows = [r for r in reader if r]
    try:
        data = np.array([[float(v) if v.strip() else np.nan for v in r] for r in rows], dtype=np.float64)
    except ValueError as exc:
        raise RecordingError(f"{path}: non-numeric value ({exc})") from exc
    if data.ndim != 2 or data.shape[1] != len(header):
        raise RecordingError(f"{path}: rows do not match the header's {len(header)} columns")

    def col(name: str) -> np.ndarray:
        return data[:, index[name]]

    force = np.stack(
        [np.stack([col(f"S0_P{p}_F{a}") for a in _AXES], -1) for p in range(N_PILLARS)], 1
    )
    disp = np.stack(
        [np.stack([col(f"S0_P{p}_D{a}") for a in _AXES], -1) for p in range(N_PILLARS)], 1
    )
    slip = None
    if all(c in index for c in _TRUTH_SLIP):
        slip = np.stack([col(c) for c in _TRUTH_SLIP], 1) > 0.5
    label = col("SLIPD_label").astype(np.uint8) if "SLIPD_label" in index else None
    motion = None
    if all(c in index for c in _TRUTH_REST[1:]):
        motion = np.stack([col(c) for c in _TRUTH_REST[1:]], 1)
    return Recording(
        t_us=col("T_us").astype(np.int64),
        force=force,
        disp=disp,
        slip=slip,
        label=label,
        object_motion=motion,
        meta=meta,
    )


def list_recordings(folder: str | Path) -> list[Path]:
    """All ``.npz`` and ``.csv`` recordings below ``folder``, sorted by name."""
    folder = Path(folder)
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".npz", ".csv") and p.is_file())
