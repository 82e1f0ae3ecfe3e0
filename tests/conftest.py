"""Shared test fixtures: repository paths and the optional shared reference material."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slipd.geometry import CENTRE, CORNERS, OUTER, PILLAR_XY_MM
from slipd.recording import Recording

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REFERENCE_CKPT = SHARED / "reference" / "checkpoints" / "hexapod"


@pytest.fixture
def reference_ckpt_dir() -> Path:
    """The authors' checkpoints, or skip where ../shared is absent."""
    if not (REFERENCE_CKPT / "ckpt_final_model_0.pth").exists():
        pytest.skip("reference checkpoints not present (../shared/reference/checkpoints/hexapod)")
    return REFERENCE_CKPT


@pytest.fixture(scope="session")
def tiny_model_json(tmp_path_factory) -> Path:
    """A small randomly initialised ensemble (default feature layout, 3 members, hidden 16) exported to ONNX.

    Random weights with non-trivial BatchNorm statistics: enough to exercise the runtime paths quickly.
    """
    torch = pytest.importorskip("torch")
    from slipd.detect.features import FeatureSpec
    from sliplab.export import export, fold_member
    from sliplab.model import SlipNet

    spec = FeatureSpec()
    nets = []
    for seed in range(3):
        torch.manual_seed(seed)
        net = SlipNet(input_size=spec.input_size, hidden=16, enc=32, pred=(16, 8))
        with torch.no_grad():
            for m in net.modules():
                if isinstance(m, torch.nn.BatchNorm1d):
                    m.running_var.uniform_(0.5, 1.5)
                    m.running_mean.normal_(0, 0.2)
        nets.append(net.eval())
    out = tmp_path_factory.mktemp("tiny_model") / "tiny.onnx"
    export([fold_member(n.state_dict()) for n in nets], spec, out, "trained", {"note": "test fixture"})
    return out.with_suffix(".json")


@pytest.fixture(scope="session")
def detect_model_json(tmp_path_factory) -> Path:
    """A model that really detects slip: the shipped one, else the authors' checkpoints converted (or skip)."""
    shipped = ROOT / "slipd" / "models" / "slip_ensemble.json"
    if shipped.exists():
        return shipped
    if not (REFERENCE_CKPT / "ckpt_final_model_0.pth").exists():
        pytest.skip("no shipped model and no reference checkpoints")
    pytest.importorskip("torch")
    from sliplab.export import export, load_reference

    members, spec, prov = load_reference(REFERENCE_CKPT)
    out = tmp_path_factory.mktemp("reference") / "reference.onnx"
    export(members, spec, out, "reference-hexapod", prov)
    return out.with_suffix(".json")


# ------------------------------------------------------------------ a synthetic slip scene (shared helpers)
K_T = 3.5  # N/mm
FZ = np.array([1.0 if i in CORNERS else 3.0 if i == CENTRE else 2.0 for i in range(9)])


def make_scene(
    kind: str = "slip",
    motion: str = "translation",
    speed: float = 2.0,
    duration_s: float = 1.5,
    move_s: float = 0.6,
    stop_s: float | None = None,
    noise: float = 0.01,
    seed: int = 0,
    direction_deg: float = 30.0,
) -> Recording:
    """A kinematic stick-slip scene: press, then the surface moves; a tip sticks until its deflection reaches
    mu F_z / k_t (mu = 1), then slides. Corners (lightest load) slip first, the centre last.

    ``speed`` is mm/s for translations and deg/s for rotations about the centre pillar. ``stop_s``: the
    surface halts at this time (a stop trial when it halts before any tip slips).
    """
    rng = np.random.default_rng(seed)
    n = int(duration_s * 1000)
    t = np.arange(n) / 1000.0
    press = np.clip((t - 0.1) / 0.2, 0.0, 1.0)
    fz = press[:, None] * FZ[None, :]
    moving_t = np.clip(t - move_s, 0.0, None if stop_s is None else stop_s - move_s)
    if motion == "rotation":
        theta = np.deg2rad(speed * moving_t)
        c, s = np.cos(theta), np.sin(theta)
        xy = PILLAR_XY_MM
        surf = np.stack([c[:, None] * xy[:, 0] - s[:, None] * xy[:, 1] - xy[:, 0],
                         s[:, None] * xy[:, 0] + c[:, None] * xy[:, 1] - xy[:, 1]], axis=-1)
        obj = np.stack([np.zeros(n), np.zeros(n), np.rad2deg(theta)], axis=1)
    else:
        d = np.deg2rad(direction_deg)
        step = speed * moving_t
        surf = np.repeat((step[:, None] * np.array([np.cos(d), np.sin(d)]))[:, None, :], 9, axis=1)
        obj = np.stack([step * np.cos(d), step * np.sin(d), np.zeros(n)], axis=1)
    limit = fz / K_T
    mag = np.linalg.norm(surf, axis=-1)
    slid = (mag >= limit) & (mag > 0)
    scale = np.where(slid, limit / np.maximum(mag, 1e-12), 1.0)
    u = surf * scale[..., None]
    # Sliding = at the friction limit while the surface still moves.
    still_moving = np.r_[np.diff(moving_t) > 0, False]
    slip = slid & still_moving[:, None]
    considered = list(OUTER) if motion == "rotation" else list(range(9))
    ever = np.maximum.accumulate(slip[:, considered], axis=0)
    label = (ever.any(axis=1) & ~ever.all(axis=1)).astype(np.uint8)
    force = np.concatenate([K_T * u, fz[..., None]], axis=-1).astype(np.float32)
    force += rng.normal(0, 1, force.shape).astype(np.float32) * np.array([noise, noise, 2 * noise], np.float32)
    disp = np.concatenate([u, (fz / 9.0)[..., None]], axis=-1).astype(np.float32)
    disp[..., :2] += rng.normal(0, noise / K_T, u.shape).astype(np.float32)
    events = {"motion_start": move_s}
    if stop_s is not None:
        events["motion_stop"] = stop_s
    if label.any():
        on = int(np.argmax(label))
        events["onset"] = float(t[on])
        after = np.flatnonzero(label[on:] == 0)
        if len(after):
            events["gross_slip"] = float(t[on + after[0]])
    return Recording(
        t_us=np.arange(n, dtype=np.int64) * 1000, force=force, disp=disp, slip=slip, label=label,
        object_motion=obj, meta={"kind": kind, "motion": motion, "events": events, "tare_samples": [0, 100]},
    )


def still_hold(n: int = 5000) -> Recording:
    """A steady press with sensor noise on every pillar (1.5 N each): a stream the daemon stays live on, quiet."""
    rng = np.random.default_rng(0)
    force = np.zeros((n, 9, 3), np.float32)
    force[:, :, 2] = 1.5
    force += rng.normal(0, 0.01, force.shape).astype(np.float32)
    return Recording(t_us=np.arange(n) * 1000, force=force, disp=np.zeros((n, 9, 3)))


def slip_and_hold_folder(folder: Path) -> Path:
    """A folder of two recordings the lab's tools score by kind: one slip scene and one still hold (kind ``hold``)."""
    folder.mkdir()
    make_scene("slip", seed=1).save(folder / "slip.npz")
    hold = still_hold(3000)
    hold.meta = {"kind": "hold", "tare_samples": [0, 100]}
    hold.save(folder / "hold.npz")
    return folder


def run_streamed(daemon: Any, dev: Any, seconds: float, settle_s: float) -> tuple[Any, list[Any]]:
    """Run ``daemon`` for ``seconds``, the emulated devices ``dev`` streaming from the moment it is ready; then give
    its device threads ``settle_s`` to finish what the run sent. Returns (the loop's stats, the servo's writes)."""

    async def main() -> Any:
        task = asyncio.create_task(daemon.run(duration_s=seconds))
        await daemon.ready.wait()
        dev.start_sensor()
        return await task

    stats = asyncio.run(main())
    time.sleep(settle_s)
    return stats, dev.servo.writes()
