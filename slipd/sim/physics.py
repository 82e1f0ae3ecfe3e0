"""PapillArray contact physics: nine compliant pillars with stick-slip tips, vectorised over a batch.

Units: mm, N, s, kg, degrees only at the API edge (radians inside). Arrays carry a leading batch
axis ``B`` (many scenes advance together in one time loop, which is how data sets reach hundreds of
times real time on one core) followed by the pillar axis (9, SDK order, ``slipd.geometry``).

Model (one implementation of each idea; both the open-loop scene generator and the closed-loop
steppers call these functions):

* ``compression``      c_i = max(0, d - dh_i - offset_i) for pillars in contact (0 otherwise);
                        dh_i = unloaded tip height below the centre (corners 0.5 mm, edges 0.2 mm),
                        offset_i = tilt / curvature / partial-contact terms from effects.
* ``normal_force``     F_z = a c / (1 + b c): secant stiffness a/(1+bc) falls from ~9 N/mm near
                        0.2 mm to ~5 N/mm near 2 mm (v2; v1 is harder).
* ``surface_delta``    displacement, over one step, of the surface material point lying over each
                        pillar when the surface pose (translation T, rotation theta) changes.
* ``stick_slip_step``  tips stick to the surface (deflection u follows the surface, F_t = k_t u)
                        until |F_t| >= mu_s F_z; then they slide with |F_t| = mu_k F_z (a radial
                        return onto the kinetic friction circle, i.e. a massless tip under Coulomb
                        friction) until the relative speed falls to zero (the trial deflection comes
                        back inside the kinetic circle), when they stick again. Slip truth = sliding.
* Press splay          while a pillar is compressed its tip splays radially outward by
                        ``splay * dc`` (a constant press-induced tangential offset once pressed).

Steppers (closed-loop rig API)
------------------------------
``HexapodStepper(sensor, batch=1)``: the surface pose is the input.
    ``reset(contact_offset=None, contact_mask=None)``
    ``step(T_mm [B,2], theta_deg [B], depth_mm [B]) -> StepOut``

``GripperStepper(sensor, obj, batch=1, contact_offset=None, contact_mask=None, table=False)``: an
object held between the sensor finger and a rigid finger (``table``: the object starts resting on a
table, which carries its weight until the grasp lifts it off, along +y). Inputs per sample: grip
force from the servo (N); the finger's acceleration (mm/s^2, sensor plane x/y; the stepper
integrates it into the finger's motion); the external load on the object as an acceleration
(mm/s^2 in the sensor plane: gravity, plus e.g. table drag / mass while pushing); and the
centre-of-mass offset of an off-centre grasp (mm; its load twists the grasp).
    ``reset()``
    ``step(grip_n [B], accel_mm_s2 [B,2], load_mm_s2 [B,2], com_offset_mm [B,2]) -> StepOut``
``StepOut``: ``force [B,9,3]`` (N, true, unsaturated), ``disp [B,9,3]`` (mm: tip deflection x/y and
compression z), ``slip [B,9]`` (bool), ``object_motion [B,3]`` (mm, mm, deg of the object relative
to the finger; the surface pose for the hexapod). Both steppers advance one sample of ``DT_S``;
call ``step`` n times to advance n samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slipd.geometry import FT_RANGE_N, FZ_RANGE_N, HEIGHT_OFFSET_MM, N_PILLARS, PILLAR_XY_MM

DT_S = 1e-3
"""One sample at 1 kHz."""
_TINY = 1e-12


@dataclass(frozen=True)
class SensorParams:
    """Mechanical parameters of one PapillArray version."""

    name: str
    kt_n_mm: float
    """Tangential tip stiffness, F_t = kt u."""
    kn_a: float
    """Normal force law F_z = a c / (1 + b c), a in N/mm."""
    kn_b: float
    """... and b in 1/mm."""
    splay: float
    """Radial tip splay per mm of compression (press-induced tangential offset)."""
    ft_range_n: float = FT_RANGE_N
    fz_range_n: float = FZ_RANGE_N

    def to_dict(self) -> dict:
        """JSON-friendly form for recording metadata."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


SENSORS: dict[str, SensorParams] = {
    # v2: published tangential ~3.5 N/mm, normal secant 9.1 N/mm at 0.2 mm and 5.0 N/mm at 2 mm.
    "v2": SensorParams("v2", kt_n_mm=3.5, kn_a=10.0, kn_b=0.5, splay=0.12),
    # v1 (Dev Kit v1, the hexapod data): larger, harder pillars.
    "v1": SensorParams("v1", kt_n_mm=5.0, kn_a=13.0, kn_b=0.5, splay=0.12),
}


def sensor_params(name: str) -> SensorParams:
    """The parameter set of sensor version ``name`` ("v1" or "v2")."""
    try:
        return SENSORS[name]
    except KeyError:
        raise ValueError(f"unknown sensor version {name!r}; known: {sorted(SENSORS)}") from None


_R = np.hypot(PILLAR_XY_MM[:, 0], PILLAR_XY_MM[:, 1])
RADIAL_UNIT = np.where(_R[:, None] > 0, PILLAR_XY_MM / np.maximum(_R, _TINY)[:, None], 0.0)
"""[9, 2] unit vector from the centre to each pillar (zero for the centre)."""


# ---------------------------------------------------------------------------- contact laws
def compression(depth_mm: np.ndarray, contact_offset: np.ndarray | None = None,
                contact_mask: np.ndarray | None = None) -> np.ndarray:
    """Pillar compression (mm) for a surface pressed ``depth_mm`` past the centre tip.

    ``depth_mm`` [...]; ``contact_offset`` [..., 9] extra height (mm) by which the surface misses each
    pillar (tilt, curvature); ``contact_mask`` [..., 9] bool, False = pillar not touched at all.
    Returns [..., 9], never negative.
    """
    d = np.asarray(depth_mm, dtype=np.float64)[..., None]
    off = HEIGHT_OFFSET_MM if contact_offset is None else HEIGHT_OFFSET_MM + contact_offset
    c = np.maximum(d - off, 0.0)
    if contact_mask is not None:
        c = np.where(contact_mask, c, 0.0)
    return c


def normal_force(c_mm: np.ndarray, sensor: SensorParams) -> np.ndarray:
    """Normal force (N) of compressed pillars: F = a c / (1 + b c), stiffening sub-linearly."""
    c = np.maximum(np.asarray(c_mm, dtype=np.float64), 0.0)
    return sensor.kn_a * c / (1.0 + sensor.kn_b * c)


def compression_for_force(fz_n: np.ndarray, sensor: SensorParams) -> np.ndarray:
    """Inverse of ``normal_force``: compression (mm) giving normal force ``fz_n`` (N)."""
    f = np.maximum(np.asarray(fz_n, dtype=np.float64), 0.0)
    return f / np.maximum(sensor.kn_a - sensor.kn_b * f, _TINY)


def depth_for_total_force(total_n: np.ndarray, sensor: SensorParams, contact_offset: np.ndarray | None = None,
                          contact_mask: np.ndarray | None = None, max_depth_mm: float = 4.0) -> np.ndarray:
    """Surface depth at which the pillars together push back with ``total_n`` (N); [B] -> [B].

    The total force is monotone in depth, so a fixed-count bisection (vectorised over the batch) is
    exact to ~1e-9 mm and never fails. Forces above what ``max_depth_mm`` gives return that depth.
    """
    total = np.asarray(total_n, dtype=np.float64)
    lo = np.zeros_like(total)
    hi = np.full_like(total, max_depth_mm)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        f = normal_force(compression(mid, contact_offset, contact_mask), sensor).sum(-1)
        below = f < total
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def friction_limits(fz_n: np.ndarray, mu_s: np.ndarray | float, mu_k: np.ndarray | float,
                    sensor: SensorParams) -> tuple[np.ndarray, np.ndarray]:
    """Static and kinetic deflection limits (mm): mu F_z / k_t. [..., 9] each."""
    fz = np.asarray(fz_n, dtype=np.float64)
    return np.asarray(mu_s)[..., None] * fz / sensor.kt_n_mm, np.asarray(mu_k)[..., None] * fz / sensor.kt_n_mm


def rotation_matrix(theta_rad: np.ndarray) -> np.ndarray:
    """[..., 2, 2] rotation matrices."""
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def surface_delta(t0: np.ndarray, th0: np.ndarray, t1: np.ndarray, th1: np.ndarray,
                  xy: np.ndarray = PILLAR_XY_MM) -> np.ndarray:
    """Displacement (mm) of the surface material point over each pillar base between two poses.

    A pose maps surface coordinates q to sensor coordinates R(theta) q + T. The point over base x at
    pose 0 moves to R(th1 - th0)(x - T0) + T1. ``t0, t1`` [..., 2] mm; ``th0, th1`` [...] rad;
    returns [..., 9, 2]. Works on any leading shape (one step, or all steps of a scene at once).
    """
    dth = np.asarray(th1) - np.asarray(th0)
    c, s = np.cos(dth)[..., None], np.sin(dth)[..., None]
    t0, t1 = np.asarray(t0), np.asarray(t1)
    rx = xy[:, 0] - t0[..., 0:1]  # [..., 9]
    ry = xy[:, 1] - t0[..., 1:2]
    # Explicit 2-D rotation: einsum over [N, B, 9] is an order of magnitude slower.
    return np.stack([c * rx - s * ry + t1[..., 0:1] - xy[:, 0], s * rx + c * ry + t1[..., 1:2] - xy[:, 1]], -1)


def splay_delta(dc_mm: np.ndarray, sensor: SensorParams) -> np.ndarray:
    """Radial tip displacement (mm) for a compression change ``dc_mm`` [..., 9] -> [..., 9, 2]."""
    return sensor.splay * np.asarray(dc_mm)[..., None] * RADIAL_UNIT


def stick_slip_step(u: np.ndarray, delta: np.ndarray, lim_s: np.ndarray, lim_k: np.ndarray,
                    sliding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Advance tip deflections by one step of surface motion (the stick-slip law).

    ``u`` [..., 2] deflection (mm), ``delta`` [..., 2] surface displacement over the step,
    ``lim_s``/``lim_k`` [...] static/kinetic deflection limits (mm), ``sliding`` [...] bool.
    A stuck tip starts sliding when the trial deflection reaches the static limit; a sliding tip keeps
    sliding while the trial lies outside the kinetic limit (relative speed > 0). A sliding tip sits
    on the kinetic circle in the direction of the trial. Returns (u_next, sliding_next); no tip is
    ever left beyond its static limit.
    """
    trial = u + delta
    mag = np.hypot(trial[..., 0], trial[..., 1])
    # Relative tolerance: a sliding tip whose surface stopped has |trial| == lim_k up to rounding.
    slide = np.where(sliding, mag > lim_k * (1.0 + 1e-9) + 1e-12, mag >= lim_s)
    scale = np.where(slide, lim_k / np.maximum(mag, _TINY), 1.0)
    return trial * scale[..., None], slide


@dataclass
class StepOut:
    """One sample of physics output (see module docstring)."""

    force: np.ndarray
    disp: np.ndarray
    slip: np.ndarray
    object_motion: np.ndarray


def pillar_outputs(u: np.ndarray, c: np.ndarray, fz: np.ndarray, sensor: SensorParams) -> tuple[np.ndarray, np.ndarray]:
    """Assemble [..., 9, 3] force (kt u, F_z) and displacement (u, c) arrays."""
    force = np.concatenate([sensor.kt_n_mm * u, fz[..., None]], axis=-1)
    disp = np.concatenate([u, c[..., None]], axis=-1)
    return force, disp


def measured_disp(disp: np.ndarray, force_true: np.ndarray, force_measured: np.ndarray,
                  sensor: SensorParams) -> np.ndarray:
    """The tip deflection the sensor reports: the true one plus the measurement error of the forces.

    A PapillArray measures each pillar tip's displacement optically (4 photodiodes) and computes the forces
    from it by its factory calibration, so one measurement error shows in both outputs. The tangential
    force error (noise, drift, glitches, filtering, quantisation: whatever the ``signal`` effects added)
    over the tangential stiffness is therefore added to ``dx, dy``; ``dz`` stays the true compression
    (nothing reads it). Without this, the simulator reported noise-free displacements next to noisy forces,
    which flattered every detector that differentiates displacements.
    """
    out = np.array(disp, dtype=np.float64, copy=True)
    err = np.asarray(force_measured, np.float64)[..., :2] - np.asarray(force_true, np.float64)[..., :2]
    out[..., :2] += err / sensor.kt_n_mm
    return out


def saturate(force: np.ndarray, sensor: SensorParams) -> np.ndarray:
    """Clip forces to the sensor's ranges as the real sensor saturates (+-ft tangential, +-fz normal).

    The normal channel is symmetric too: physics never pushes it below 0, but measurement noise and
    drift around the tared zero do, as on the real sensor.
    """
    out = np.array(force, dtype=np.float64, copy=True)
    np.clip(out[..., :2], -sensor.ft_range_n, sensor.ft_range_n, out=out[..., :2])
    np.clip(out[..., 2], -sensor.fz_range_n, sensor.fz_range_n, out=out[..., 2])
    return out


# ---------------------------------------------------------------------------- hexapod stepper
class HexapodStepper:
    """The surface (a plate on a hexapod) is driven directly; see the module docstring for the API."""

    def __init__(self, sensor: SensorParams, batch: int = 1, mu_s: float | np.ndarray = 0.6,
                 mu_k: float | np.ndarray = 0.5) -> None:
        self.sensor = sensor
        self.batch = batch
        self.mu_s = np.broadcast_to(np.asarray(mu_s, np.float64), (batch,)).copy()
        self.mu_k = np.broadcast_to(np.asarray(mu_k, np.float64), (batch,)).copy()
        self.reset()

    def reset(self, contact_offset: np.ndarray | None = None, contact_mask: np.ndarray | None = None) -> None:
        """Unloaded, unpressed state at pose (0, 0, 0)."""
        b = self.batch
        self.contact_offset = None if contact_offset is None else np.broadcast_to(contact_offset, (b, N_PILLARS))
        self.contact_mask = None if contact_mask is None else np.broadcast_to(contact_mask, (b, N_PILLARS))
        self.u = np.zeros((b, N_PILLARS, 2))
        self.sliding = np.zeros((b, N_PILLARS), bool)
        self.c = np.zeros((b, N_PILLARS))
        self.pose_t = np.zeros((b, 2))
        self.pose_th = np.zeros(b)

    def step(self, t_mm: np.ndarray, theta_deg: np.ndarray, depth_mm: np.ndarray) -> StepOut:
        """Move the surface to pose (``t_mm`` [B,2], ``theta_deg`` [B]) at ``depth_mm`` [B]; one sample."""
        th = np.deg2rad(np.asarray(theta_deg, np.float64)).reshape(self.batch)
        t1 = np.asarray(t_mm, np.float64).reshape(self.batch, 2)
        c = compression(np.asarray(depth_mm, np.float64).reshape(self.batch), self.contact_offset, self.contact_mask)
        delta = surface_delta(self.pose_t, self.pose_th, t1, th) + splay_delta(c - self.c, self.sensor)
        fz = normal_force(c, self.sensor)
        lim_s, lim_k = friction_limits(fz, self.mu_s, self.mu_k, self.sensor)
        self.u, slide = stick_slip_step(self.u, delta, lim_s, lim_k, self.sliding)
        self.sliding = slide & (fz > 0)
        self.c, self.pose_t, self.pose_th = c, t1, th
        force, disp = pillar_outputs(self.u, c, fz, self.sensor)
        motion = np.concatenate([t1, np.rad2deg(th)[:, None]], axis=1)
        return StepOut(force, disp, self.sliding.copy(), motion)


def run_hexapod(sensor: SensorParams, t_mm: np.ndarray, theta_rad: np.ndarray, depth_mm: np.ndarray,
                mu_s: np.ndarray, mu_k: np.ndarray, contact_offset: np.ndarray | None = None,
                contact_mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Open-loop fast path: a whole batch of hexapod trajectories at once.

    ``t_mm`` [N,B,2], ``theta_rad`` [N,B], ``depth_mm`` [N,B], ``mu_s``/``mu_k`` [B],
    ``contact_offset``/``contact_mask`` [B,9]. The kinematics (surface deltas, compressions, friction
    limits) are computed for all samples at once with the same functions the stepper calls per
    sample; only the stick-slip recurrence runs in a time loop, over the whole batch.
    Returns u [N,B,9,2] tip deflections, c [N,B,9] compressions, fz [N,B,9] normal forces and
    slip [N,B,9]; ``pillar_outputs(u, c, fz, sensor)`` assembles force/disp arrays (per scene: the
    [N,B,...] arrays are large, and slicing before assembling keeps the work in cache).
    """
    n, b = depth_mm.shape
    c = compression(depth_mm, contact_offset, contact_mask)  # [N,B,9]
    c_prev = np.concatenate([np.zeros((1, b, N_PILLARS)), c[:-1]])
    t_prev = np.concatenate([np.zeros((1, b, 2)), t_mm[:-1]])
    th_prev = np.concatenate([np.zeros((1, b)), theta_rad[:-1]])
    delta = surface_delta(t_prev, th_prev, t_mm, theta_rad) + splay_delta(c - c_prev, sensor)
    fz = normal_force(c, sensor)
    lim_s, lim_k = friction_limits(fz, mu_s, mu_k, sensor)
    in_contact = fz > 0
    u_all = np.empty((n, b, N_PILLARS, 2))
    slip = np.empty((n, b, N_PILLARS), bool)
    u = np.zeros((b, N_PILLARS, 2))
    sliding = np.zeros((b, N_PILLARS), bool)
    k = 0
    retry_at = 0
    while k < n:
        if k >= retry_at and not sliding.any():
            # Fast-forward while every tip sticks: deflections are then the running sum of the
            # surface increments (np.cumsum adds sequentially, so the values are bit-identical to
            # the step-by-step law) until the first tip reaches its static limit or contact changes.
            m = _stuck_run(u, delta, lim_s, in_contact, k, min(n, k + _FF_CHUNK))
            if m:
                u_all[k: k + m] = _stuck_path(u, delta[k: k + m], in_contact[k])
                slip[k: k + m] = False
                u = u_all[k + m - 1].copy()
                k += m
            if m < 8:
                retry_at = k + 32  # a limit is near: step normally for a while
            if k >= n:
                break
        u, slide = stick_slip_step(u, delta[k], lim_s[k], lim_k[k], sliding)
        sliding = slide & in_contact[k]
        u_all[k] = u
        slip[k] = sliding
        k += 1
    return {"u": u_all, "c": c, "fz": fz, "slip": slip}


_FF_CHUNK = 512


def _stuck_path(u: np.ndarray, deltas: np.ndarray, in_contact: np.ndarray) -> np.ndarray:
    """Deflections over ``deltas`` [M,B,9,2] if every tip sticks (tips out of contact stay at 0)."""
    path = np.cumsum(np.concatenate([u[None], deltas]), axis=0)[1:]
    return np.where(in_contact[None, ..., None], path, 0.0)


def _stuck_run(u: np.ndarray, delta: np.ndarray, lim_s: np.ndarray, in_contact: np.ndarray, k: int,
               end: int) -> int:
    """How many samples from ``k`` all tips stay stuck (no static limit reached, contact unchanged)."""
    same = np.all(in_contact[k:end] == in_contact[k], axis=(1, 2))
    end = k + (int(np.argmin(same)) if not same.all() else end - k)
    if end <= k:
        return 0
    path = _stuck_path(u, delta[k:end], in_contact[k])
    mag = np.hypot(path[..., 0], path[..., 1])
    hit = np.any((mag >= lim_s[k:end]) & in_contact[k:end], axis=(1, 2))
    return int(np.argmax(hit)) if hit.any() else end - k


# ---------------------------------------------------------------------------- gripper stepper
@dataclass(frozen=True)
class ObjectParams:
    """A grasped object and its contacts (one scene's values; batched by ``GripperStepper``)."""

    mass_kg: float
    mu_s: float
    mu_k: float
    size_mm: float = 60.0
    """Characteristic size: sets the moment of inertia (a cube of this edge)."""
    rigid_kt_n_mm: float = 30.0
    """Tangential stiffness of the rigid finger's pad contact."""
    rigid_radius_mm: float = 5.0
    """Effective radius of the rigid finger's contact patch (torsional friction)."""
    damping_ratio: float = 0.3
    """Damping of the object's motion on its stuck contacts (fraction of critical)."""


class GripperStepper:
    """Object between the sensor finger and a rigid finger; see the module docstring for the API.

    The object's pose s = (x, y, phi) relative to the finger obeys m s'' = loads - contact forces
    (semi-implicit Euler at 1 kHz, sub-stepped for very light objects). Contacts: the nine pillars
    (stick-slip tips, normal forces from the grip force) and the rigid finger's pad (one
    translational and one torsional stick-slip element with Coulomb limits mu * grip).
    """

    MAX_OMEGA_DT = 0.8
    """Largest contact-mode angular frequency x sub-step allowed (semi-implicit Euler is stable below 2)."""

    def __init__(self, sensor: SensorParams, objects: list[ObjectParams] | ObjectParams, batch: int = 1,
                 contact_offset: np.ndarray | None = None, contact_mask: np.ndarray | None = None,
                 table: bool | np.ndarray = False) -> None:
        objs = [objects] * batch if isinstance(objects, ObjectParams) else list(objects)
        self.table = np.broadcast_to(np.asarray(table, bool), (batch,)).copy()
        if len(objs) != batch:
            raise ValueError(f"{len(objs)} objects for a batch of {batch}")
        self.sensor = sensor
        self.batch = batch
        self.objects = objs

        def arr(name: str) -> np.ndarray:
            return np.array([getattr(o, name) for o in objs], np.float64)

        self.mass = arr("mass_kg")
        self.mu_s, self.mu_k = arr("mu_s"), arr("mu_k")
        size_m = arr("size_mm") * 1e-3
        self.inertia = self.mass * size_m**2 / 6.0  # kg m^2, cube about an edge-normal axis
        self.kr, self.rr = arr("rigid_kt_n_mm"), arr("rigid_radius_mm")
        self.zeta = arr("damping_ratio")
        # Sub-steps from the stiffest contact mode of the lightest object: one for ordinary objects.
        k_max = (N_PILLARS * sensor.kt_n_mm + self.kr.max()) * 1e3  # N/m
        omega = float(np.sqrt(k_max / self.mass.min()))
        self.substeps = max(1, int(np.ceil(omega * DT_S / self.MAX_OMEGA_DT)))
        self.contact_offset = None if contact_offset is None else np.broadcast_to(contact_offset, (batch, N_PILLARS))
        self.contact_mask = None if contact_mask is None else np.broadcast_to(contact_mask, (batch, N_PILLARS))
        self.reset()

    def reset(self) -> None:
        """Object at rest, centred, no contact deflection."""
        b = self.batch
        self.pose = np.zeros((b, 3))  # x mm, y mm, phi rad
        self.vel = np.zeros((b, 3))  # mm/s, mm/s, rad/s
        self.u = np.zeros((b, N_PILLARS, 2))
        self.sliding = np.zeros((b, N_PILLARS), bool)
        self.c = np.zeros((b, N_PILLARS))
        self.ur = np.zeros((b, 2))  # rigid pad deflection (mm)
        self.r_sliding = np.zeros(b, bool)
        self.ur_rot = np.zeros((b, 2))  # torsional pad "deflection" (rad, 0)
        self.rot_sliding = np.zeros(b, bool)
        self.finger_pos = np.zeros((b, 2))
        self.finger_vel = np.zeros((b, 2))
        self._last_grip: np.ndarray | None = None
        self._contact_key: np.ndarray | None = None
        self._contact: tuple[np.ndarray, ...] = ()
        self._depth = np.zeros(b)

    def step(self, grip_n: np.ndarray, accel_mm_s2: np.ndarray, load_mm_s2: np.ndarray,
             com_offset_mm: np.ndarray) -> StepOut:
        """Advance one sample; see the module docstring for the inputs."""
        b, sensor = self.batch, self.sensor
        grip = np.maximum(np.asarray(grip_n, np.float64).reshape(b), 0.0)
        if self._last_grip is None or not np.array_equal(grip, self._last_grip):
            # The bisection costs ~40 force evaluations; the servo changes the grip far less often.
            self._depth = depth_for_total_force(grip, sensor, self.contact_offset, self.contact_mask)
            self._last_grip = grip
        return self.advance(grip, self._depth, accel_mm_s2, load_mm_s2, com_offset_mm)

    def advance(self, grip_n: np.ndarray, depth_mm: np.ndarray, accel_mm_s2: np.ndarray, load_mm_s2: np.ndarray,
                com_offset_mm: np.ndarray) -> StepOut:
        """``step`` with the sensor depth for the grip force already solved (the open-loop fast path
        solves all samples at once with ``depth_for_total_force``)."""
        b, sensor = self.batch, self.sensor
        grip = np.maximum(np.asarray(grip_n, np.float64).reshape(b), 0.0)
        depth = np.asarray(depth_mm, np.float64).reshape(b)
        if self._contact_key is None or not np.array_equal(depth, self._contact_key):
            # The contact state only changes with the grip: recompute it only then.
            c = compression(depth, self.contact_offset, self.contact_mask)
            fz = normal_force(c, sensor)
            self._contact = (c, fz, *friction_limits(fz, self.mu_s, self.mu_k, sensor))
            self._contact_key = depth
        c, fz, lim_s, lim_k = self._contact
        # Rigid pad: translational limit mu*grip/kr (mm), torsional limit mu*grip*r/(kr r^2) (rad).
        rl_s, rl_k = self.mu_s * grip / self.kr, self.mu_k * grip / self.kr
        krot = self.kr * self.rr**2  # N mm / rad
        tl_s, tl_k = self.mu_s * grip * self.rr / krot * 0.67, self.mu_k * grip * self.rr / krot * 0.67
        # Object loads relative to the finger (N and N mm): gravity and the pseudo-force of the
        # finger's acceleration act at the centre of mass.
        accel = np.asarray(accel_mm_s2, np.float64).reshape(b, 2)
        acc = np.asarray(load_mm_s2, np.float64).reshape(b, 2) - accel
        load = self.mass[:, None] * acc * 1e-3
        arm0 = np.asarray(com_offset_mm, np.float64).reshape(b, 2)
        # The centre of mass turns with the object, so an off-centre object swings towards hanging.
        cphi, sphi = np.cos(self.pose[:, 2]), np.sin(self.pose[:, 2])
        arm = np.stack([cphi * arm0[:, 0] - sphi * arm0[:, 1], sphi * arm0[:, 0] + cphi * arm0[:, 1]], 1)
        torque = arm[:, 0] * load[:, 1] - arm[:, 1] * load[:, 0]
        dt = DT_S / self.substeps
        u, sliding = self.u, self.sliding
        splay = splay_delta(c - self.c, sensor)
        in_contact = fz > 0
        for sub in range(self.substeps):
            ft = sensor.kt_n_mm * u  # force on the pillars, so -ft on the object
            f_obj = load - ft.sum(1) - self.kr[:, None] * self.ur
            tz_pillars = (PILLAR_XY_MM[:, 0] * ft[..., 1] - PILLAR_XY_MM[:, 1] * ft[..., 0]).sum(1)
            t_obj = torque - tz_pillars - krot * self.ur_rot[:, 0]
            # Damping on the stuck contacts only (a sliding contact dissipates by friction).
            k_lin = sensor.kt_n_mm * (~sliding & in_contact).sum(1) + self.kr * ~self.r_sliding
            c_lin = 2 * self.zeta * np.sqrt(k_lin * 1e3 * self.mass)  # N s / m
            r2 = (PILLAR_XY_MM**2).sum(1)
            k_rot = (sensor.kt_n_mm * (~sliding & in_contact) * r2).sum(1) + krot * ~self.rot_sliding
            c_rot = 2 * self.zeta * np.sqrt(k_rot * 1e-3 * self.inertia)  # N m s / rad
            lin_acc = (f_obj - c_lin[:, None] * self.vel[:, :2] * 1e-3) / self.mass[:, None] * 1e3  # mm/s^2
            rot_acc = (t_obj * 1e-3 - c_rot * self.vel[:, 2]) / self.inertia  # rad/s^2
            self.vel[:, :2] += lin_acc * dt
            self.vel[:, 2] += rot_acc * dt
            old_pose = self.pose.copy()
            self.pose += self.vel * dt
            # The finger moves with the commanded acceleration (world frame, +y up).
            self.finger_vel += accel * dt
            self.finger_pos += self.finger_vel * dt
            if self.table.any():
                # A table under the object (unilateral, +y): it cannot sink below its start height;
                # while it rests there the table also stops it turning.
                world_y = self.finger_pos[:, 1] + self.pose[:, 1]
                down = self.table & (world_y < 0.0)
                if down.any():
                    self.pose[down, 1] = -self.finger_pos[down, 1]
                    self.vel[down, 1] = np.maximum(self.vel[down, 1], -self.finger_vel[down, 1])
                    self.pose[down, 2] = old_pose[down, 2]
                    self.vel[down, 2] = 0.0
            d_pose = self.pose - old_pose
            # Material points over the pillars move with the object's increment (a rigid-body move
            # about the object's grasp centre: the same surface kinematics as the hexapod's plate).
            delta = surface_delta(old_pose[:, :2], np.zeros(b), self.pose[:, :2], d_pose[:, 2])
            if sub == 0:
                delta = delta + splay
            u, slide = stick_slip_step(u, delta, lim_s, lim_k, sliding)
            sliding = slide & in_contact
            self.ur, self.r_sliding = stick_slip_step(self.ur, d_pose[:, :2], rl_s, rl_k, self.r_sliding)
            rot_delta = np.stack([d_pose[:, 2], np.zeros(b)], 1)
            self.ur_rot, self.rot_sliding = stick_slip_step(self.ur_rot, rot_delta, tl_s, tl_k, self.rot_sliding)
        self.u, self.sliding, self.c = u, sliding, c
        force, disp = pillar_outputs(u, c, fz, sensor)
        motion = np.concatenate([self.pose[:, :2], np.rad2deg(self.pose[:, 2:3])], axis=1)
        return StepOut(force, disp, sliding.copy(), motion)
