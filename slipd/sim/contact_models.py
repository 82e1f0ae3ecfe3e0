"""Physics families: contact models registered by name, selected by a scene (``physics: {name: ...}``).

A detector must be judged on physics it was not trained on, so the simulator carries several tangential
contact laws beside today's one. Each family is a small class registered by name (like the effects in
``slipd.sim.effects``) with a pydantic ``Params`` model; every family also accepts two options:

* ``spread``       per-pillar manufacturing spread: tangential stiffness (log-normal sigma ``kt``), tip
                   height (normal sigma ``height_mm``, the most protruding tip touching first) and friction
                   (log-normal sigma ``mu``), drawn from the scene seed.
* ``calibration``  per-pillar calibration error of the reported forces: an axis rotation (normal sigma
                   ``rot_deg``) and a gain (log-normal sigma ``gain``). It acts on the measurement, never on
                   the truth (slip, labels).

Families (hexapod scenes; gripper scenes keep the default):

``stick_slip``    today's model (Coulomb stick-slip with a static and a kinetic limit, ``physics.run_hexapod``).
                  The default: without options it runs exactly the code it always ran (bit-identical).
``viscoelastic``  a standard linear solid in the tangential direction: a spring ``(1 - ratio) kt`` in
                  parallel with a Maxwell branch (spring ``ratio kt``, relaxation time ``tau_s``). Fast
                  loading sees ``kt``, slow loading ``(1 - ratio) kt``; after a halt the force relaxes
                  while the tip stays put. Friction as in stick-slip, on the total force.
``mujoco``        the MuJoCo engine (``slipd.sim.engine``): physics none of the families above shares code with. It
                  runs engine scenes (``family: engine``) only; its parameters are the solver's settings.
``bullet``        the same engine scenes on Bullet (``slipd.sim.engine.bullet``), a second physics code base: rigid
                  contacts solved by sequential impulses on a box friction cone, where MuJoCo's are soft constraints
                  on an elliptic cone.
``stribeck``      velocity-weakening friction: while sliding, mu(v) = mu_k + (mu_s - mu_k) exp(-v / v_s)
                  (v the tip's slip speed), and neighbouring tips are coupled through the membrane by a
                  spring ``coupling kt`` between their deflections (a tip that slips unloads or loads its
                  neighbours).

All non-default runs share one vectorised time loop (``run_general``): state per scene and pillar, per-scene
and per-pillar parameters as arrays, so a batch may mix families and parameter values.
"""

from __future__ import annotations

import zlib
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from slipd.geometry import HEIGHT_OFFSET_MM, N_PILLARS, PILLAR_XY_MM
from slipd.sim.effects import scene_params
from slipd.sim.engine.model import BulletParams, EngineParams
from slipd.sim.physics import (
    DT_S,
    SensorParams,
    compression,
    normal_force,
    splay_delta,
    surface_delta,
)

DEFAULT = "stick_slip"
_TINY = 1e-12


class _P(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Spread(_P):
    kt: float = Field(0.1, ge=0.0, le=0.5)
    """Log-normal sigma of the per-pillar tangential stiffness."""
    height_mm: float = Field(0.03, ge=0.0, le=0.2)
    """Normal sigma of the per-pillar tip height."""
    mu: float = Field(0.1, ge=0.0, le=0.5)
    """Log-normal sigma of the per-pillar friction (static and kinetic together)."""


class Calibration(_P):
    rot_deg: float = Field(3.0, ge=0.0, le=20.0)
    """Normal sigma of each pillar's tangential axis rotation."""
    gain: float = Field(0.05, ge=0.0, le=0.3)
    """Log-normal sigma of each pillar's gain (all three axes)."""


class ModelParams(_P):
    """Options every family accepts."""

    spread: Spread | None = None
    calibration: Calibration | None = None


class ContactModel:
    """A physics family: ``name``, a ``Params`` model, and its per-scene coefficients for ``run_general``."""

    name: ClassVar[str]
    Params: ClassVar[type[BaseModel]] = ModelParams
    engine: ClassVar[bool] = False
    """True for the engine family: its scenes run on the engine, not on ``run_general``."""

    def __init__(self, params: ModelParams) -> None:
        self.p = params

    @property
    def default_path(self) -> bool:
        """True when the scene runs ``physics.run_hexapod`` unchanged."""
        return False

    def coefficients(self) -> dict[str, float]:
        """Per-scene coefficients of the general loop: ``ratio``, ``tau_s``, ``vs_mm_s`` (0: Coulomb, the kinetic
        limit at once), ``coupling``."""
        return {"ratio": 0.0, "tau_s": 1.0, "vs_mm_s": 0.0, "coupling": 0.0}


REGISTRY: dict[str, type[ContactModel]] = {}


def register(cls: type[ContactModel]) -> type[ContactModel]:
    """Class decorator: make a contact model available to scenes by its name."""
    REGISTRY[cls.name] = cls
    return cls


@register
class StickSlip(ContactModel):
    name = "stick_slip"

    @property
    def default_path(self) -> bool:
        return self.p.spread is None


class ViscoParams(ModelParams):
    ratio: float = Field(0.4, ge=0.0, le=0.9)
    """Share of the fast stiffness that relaxes (the Maxwell branch)."""
    tau_s: float = Field(0.3, gt=0.0, le=100.0)
    """Relaxation time of the Maxwell branch."""


@register
class Viscoelastic(ContactModel):
    name = "viscoelastic"
    Params = ViscoParams

    def coefficients(self) -> dict[str, float]:
        return {**super().coefficients(), "ratio": self.p.ratio, "tau_s": self.p.tau_s}


class StribeckParams(ModelParams):
    vs_mm_s: float = Field(1.0, gt=0.0, le=100.0)
    """Stribeck speed: the friction falls from mu_s towards mu_k over this slip speed."""
    coupling: float = Field(0.2, ge=0.0, le=1.0)
    """Membrane spring between neighbouring tips, as a fraction of the tangential stiffness."""


@register
class Stribeck(ContactModel):
    name = "stribeck"
    Params = StribeckParams

    def coefficients(self) -> dict[str, float]:
        return {**super().coefficients(), "vs_mm_s": self.p.vs_mm_s, "coupling": self.p.coupling}


@register
class Mujoco(ContactModel):
    name = "mujoco"
    Params = EngineParams
    engine = True


@register
class Bullet(ContactModel):
    name = "bullet"
    Params = BulletParams
    engine = True


def build_model(spec: dict[str, Any] | None, where: str = "physics") -> ContactModel:
    """A contact model from its scene entry ``{name: ..., <params>}`` (None: the default)."""
    spec = {"name": DEFAULT} if spec is None else spec
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: must be a mapping with a 'name' (one of {sorted(REGISTRY)})")
    name = spec.get("name", DEFAULT)
    if name not in REGISTRY:
        raise ValueError(f"{where}.name: unknown contact model {name!r}; known: {sorted(REGISTRY)}")
    cls = REGISTRY[name]
    return cls(scene_params(cls.Params, spec, where))


def model_rng(seed: int, what: str) -> np.random.Generator:
    """Independent generator per (scene seed, purpose): spread and calibration draw separately."""
    return np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(f"physics.{what}".encode())])


def pillar_spread(model: ContactModel, seed: int) -> dict[str, np.ndarray]:
    """Per-pillar factors of one scene: ``kt`` [9], ``mu`` [9] (multipliers) and ``height_mm`` [9] (added
    to the contact offset; shifted so that the most protruding tip sits at the nominal centre height)."""
    s = model.p.spread
    if s is None:
        return {"kt": np.ones(N_PILLARS), "mu": np.ones(N_PILLARS), "height_mm": np.zeros(N_PILLARS)}
    rng = model_rng(seed, "spread")
    kt = np.exp(rng.normal(0.0, s.kt, N_PILLARS))
    mu = np.exp(rng.normal(0.0, s.mu, N_PILLARS))
    h = rng.normal(0.0, s.height_mm, N_PILLARS)
    h -= (HEIGHT_OFFSET_MM + h).min()  # the first tip to touch does so at depth 0, as nominally
    return {"kt": kt, "mu": mu, "height_mm": h}


def apply_calibration(model: ContactModel, seed: int, force: np.ndarray) -> np.ndarray:
    """The forces as a miscalibrated sensor reports them ([N,9,3] -> [N,9,3]); identity without the option."""
    c = model.p.calibration
    if c is None:
        return force
    rng = model_rng(seed, "calibration")
    th = np.deg2rad(rng.normal(0.0, c.rot_deg, N_PILLARS))
    gain = np.exp(rng.normal(0.0, c.gain, N_PILLARS))
    cs, sn = np.cos(th), np.sin(th)
    out = np.array(force, np.float64, copy=True)
    fx, fy = force[..., 0], force[..., 1]
    out[..., 0] = gain * (cs * fx - sn * fy)
    out[..., 1] = gain * (sn * fx + cs * fy)
    out[..., 2] = gain * force[..., 2]
    return out


def _neighbours() -> np.ndarray:
    d = np.hypot(*(PILLAR_XY_MM[:, None, :] - PILLAR_XY_MM[None, :, :]).transpose(2, 0, 1))
    pitch = d[d > 0].min()
    return (d > 0) & (d < 1.1 * pitch)


NEIGHBOURS = _neighbours()
"""[9, 9] bool: pillars one grid pitch apart (membrane coupling)."""
LAPLACIAN = np.diag(NEIGHBOURS.sum(1)).astype(np.float64) - NEIGHBOURS
"""Graph Laplacian of the grid: (L u)_i = sum_j (u_i - u_j) over neighbours j."""


def run_general(sensor: SensorParams, t_mm: np.ndarray, theta_rad: np.ndarray, depth_mm: np.ndarray,
                mu_s: np.ndarray, mu_k: np.ndarray, contact_offset: np.ndarray, contact_mask: np.ndarray,
                kt_scale: np.ndarray, coef: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The open-loop hexapod path of every family: like ``physics.run_hexapod`` but with per-pillar
    stiffness and friction and the family's coefficients.

    ``t_mm`` [N,B,2], ``theta_rad``/``depth_mm`` [N,B], ``mu_s``/``mu_k``/``kt_scale``/``contact_offset`` [B,9],
    ``contact_mask`` [B,9] bool, ``coef`` arrays [B] (``ratio``, ``tau_s``, ``vs_mm_s``, ``coupling``).
    Per step: trial = stick; if the trial force reaches the static limit mu_s F_z (or, sliding, stays beyond
    the current kinetic limit mu(v) F_z) the tip slips back radially onto that limit, the slip increment
    s = (F_trial - F) / k_eff taken off both the deflection and the Maxwell branch.
    Returns u [N,B,9,2] (tip deflection), ft [N,B,9,2] (tangential force), c, fz [N,B,9], slip [N,B,9].
    """
    n, b = depth_mm.shape
    c = compression(depth_mm, contact_offset, contact_mask)
    c_prev = np.concatenate([np.zeros((1, b, N_PILLARS)), c[:-1]])
    t_prev = np.concatenate([np.zeros((1, b, 2)), t_mm[:-1]])
    th_prev = np.concatenate([np.zeros((1, b)), theta_rad[:-1]])
    delta = surface_delta(t_prev, th_prev, t_mm, theta_rad) + splay_delta(c - c_prev, sensor)
    fz = normal_force(c, sensor)
    in_contact = fz > 0
    kt = sensor.kt_n_mm * kt_scale  # [B,9] fast stiffness
    r = coef["ratio"][:, None]
    k_inf, k_1 = kt * (1.0 - r), kt * r
    decay = np.exp(-DT_S / coef["tau_s"])[:, None, None]
    kc = (coef["coupling"] * sensor.kt_n_mm)[:, None]  # [B,1]
    coupled = bool(np.any(kc > 0))
    k_eff = kt + kc * LAPLACIAN.diagonal()[None, :]
    vs = coef["vs_mm_s"][:, None]
    stribeck = vs > 0
    vs = np.maximum(vs, _TINY)
    dmu = np.where(stribeck, mu_s - mu_k, 0.0)
    u = np.zeros((b, N_PILLARS, 2))
    f1 = np.zeros((b, N_PILLARS, 2))
    v = np.zeros((b, N_PILLARS))
    sliding = np.zeros((b, N_PILLARS), bool)
    u_all = np.empty((n, b, N_PILLARS, 2))
    ft_all = np.empty((n, b, N_PILLARS, 2))
    slip = np.empty((n, b, N_PILLARS), bool)
    # Still stretches (no surface motion, no change of contact, for the whole batch): the next still
    # sample's index, so that stuck stretches can be fast-forwarded in closed form.
    # (Compared on the inputs: the surface deltas of a still pose are only zero up to rounding.)
    still = np.zeros(n, bool)
    still[1:] = (np.all(t_mm[1:] == t_mm[:-1], axis=(1, 2)) & np.all(theta_rad[1:] == theta_rad[:-1], axis=1)
                 & np.all(depth_mm[1:] == depth_mm[:-1], axis=1))
    run_end = np.empty(n + 1, np.int64)
    run_end[n] = n
    for k in range(n - 1, -1, -1):
        run_end[k] = run_end[k + 1] if still[k] else k
    k = 0
    retry_at = 0
    while k < n:
        if still[k] and k >= retry_at and not sliding.any():
            m = _still_run(u, f1, decay, k_inf, kc, coupled, mu_s * fz[k], in_contact[k], k, run_end[k + 1]
                           if k + 1 <= n else n, u_all, ft_all, slip)
            if m < 8:
                retry_at = k + m + 32  # a limit is near: step normally for a while
            if m:
                f1 = f1 * decay ** m
                v[:] = 0.0
                k += m
                continue
        d = delta[k]
        ut = u + d
        f1t = f1 * decay + k_1[..., None] * d
        ftr = k_inf[..., None] * ut + f1t
        if coupled:
            ftr = ftr + kc[..., None] * np.matmul(LAPLACIAN, ut)
        mag = np.hypot(ftr[..., 0], ftr[..., 1])
        lim_s = mu_s * fz[k]
        lim_k = (mu_k + dmu * np.exp(-v / vs)) * fz[k]
        slide = np.where(sliding, mag > lim_k * (1.0 + 1e-9) + 1e-12, mag >= lim_s)
        target = np.where(slide, lim_k / np.maximum(mag, _TINY), 1.0)
        s = ftr * ((1.0 - target) / k_eff)[..., None]
        u = ut - s
        f1 = f1t - k_1[..., None] * s
        ft = ftr * target[..., None]
        ic = in_contact[k]
        u = np.where(ic[..., None], u, 0.0)
        f1 = np.where(ic[..., None], f1, 0.0)
        ft = np.where(ic[..., None], ft, 0.0)
        v = np.hypot(s[..., 0], s[..., 1]) / DT_S
        sliding = slide & ic
        u_all[k], ft_all[k], slip[k] = u, ft, sliding
        k += 1
    return {"u": u_all, "ft": ft_all, "c": c, "fz": fz, "slip": slip}


_CHUNK = 1024


def _still_run(u, f1, decay, k_inf, kc, coupled, lim_s, ic, k, end, u_all, ft_all, slip) -> int:
    """Fast-forward a still stretch from sample ``k`` (before ``end``) while every tip sticks: the deflections
    stay, the Maxwell forces decay as decay**j. Writes the outputs and returns how many samples it covered
    (stopping before the first sample at which a static limit would be reached)."""
    base = k_inf[..., None] * u + (kc[..., None] * np.matmul(LAPLACIAN, u) if coupled else 0.0)
    done = 0
    while k + done < end:
        m = min(_CHUNK if done else 64, end - k - done)
        j = np.arange(done + 1, done + m + 1, dtype=np.float64)
        f1j = f1[None] * decay[None] ** j[:, None, None, None]  # [M,B,9,2]
        ft = base[None] + f1j
        mag = np.hypot(ft[..., 0], ft[..., 1])
        hit = np.any((mag >= lim_s[None]) & ic[None], axis=(1, 2))
        if hit.any():
            m = int(np.argmax(hit))
        ft = np.where(ic[None, ..., None], ft[:m], 0.0)
        u_all[k + done: k + done + m] = np.where(ic[..., None], u, 0.0)[None]
        ft_all[k + done: k + done + m] = ft
        slip[k + done: k + done + m] = False
        done += m
        if hit.any():
            break
    return done
