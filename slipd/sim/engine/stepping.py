"""Run the engine model over a scene's input profiles and read out what the sensor and the truth need.

Inputs per 1 kHz sample: the grip force (N), the object's effective acceleration field (m/s^2: gravity times
the share the grasp carries, minus the finger's acceleration), and an external force (N) and torque (N m) on
the object (pushes, twists, a filling load). Each sample runs ``1 ms / timestep`` engine steps; the pillars'
normal law is applied as a joint force before every step (explicit, like MuJoCo's own joint springs).

Outputs per sample: the pillar forces as the sensor computes them from its tips' deflections (``kt u`` and
the normal law of the compression), the deflections, per-pillar slip truth (the tangential speed of the
tip's contact point relative to the object's material point above ``EngineParams.slip_speed_mm_s``, while the
contact carries load and its friction force is on the friction cone, in an episode that slides it at least
``EngineParams.min_slide_mm``), the contact forces the engine's solver
found (normal and tangential, for cross-checks), and the object's pose relative to the finger (x, y mm; turn
about the sensor normal, deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from slipd.geometry import N_PILLARS
from slipd.sim.engine.model import EngineParams, ObjectGeometry, build_mjcf
from slipd.sim.physics import DT_S, SensorParams, normal_force


@dataclass
class EngineOutput:
    """Per-sample arrays of one run (N samples)."""

    force: np.ndarray
    """[N, 9, 3] N: tangential kt u and the normal law of the compression (the sensor's own forces)."""
    disp: np.ndarray
    """[N, 9, 3] mm: tip deflection x, y and compression."""
    slip: np.ndarray
    """[N, 9] bool: the tip's contact slides, in an episode that carries it at least ``min_slide_mm``."""
    contact_fn: np.ndarray
    """[N, 9] N: normal force of each tip's contact (the solver's)."""
    contact_ft: np.ndarray
    """[N, 9] N: magnitude of its friction force."""
    pose: np.ndarray
    """[N, 3]: object position x, y (mm) relative to its start, and its turn about the sensor normal (deg)."""

    @classmethod
    def allocate(cls, n: int) -> EngineOutput:
        """Arrays for ``n`` samples, filled by an engine's run (``slip`` last, from the sliding speeds)."""
        return cls(np.empty((n, N_PILLARS, 3)), np.empty((n, N_PILLARS, 3)), np.zeros((n, N_PILLARS), bool),
                   np.empty((n, N_PILLARS)), np.empty((n, N_PILLARS)), np.empty((n, 3)))


class EngineSim:
    """One scene's model and data; ``run`` advances it over input profiles."""

    def __init__(self, sensor: SensorParams, obj: ObjectGeometry, params: EngineParams) -> None:
        self.sensor, self.obj, self.params = sensor, obj, params
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(sensor, obj, params))
        self.data = mujoco.MjData(self.model)
        m = self.model
        jid = [[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"p{i}{a}") for a in "xyz"] for i in range(N_PILLARS)]
        self.qpos_adr = np.array([[m.jnt_qposadr[j] for j in row] for row in jid])  # [9, 3]
        self.dof_adr = np.array([[m.jnt_dofadr[j] for j in row] for row in jid])
        self.tip_geom = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"tip{i}") for i in range(N_PILLARS)])
        self.obj_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "object")
        self.obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        oj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object")
        self.obj_qpos, self.obj_dof = int(m.jnt_qposadr[oj]), int(m.jnt_dofadr[oj])
        self.substeps = max(1, round(DT_S / m.opt.timestep))
        self._geom_pillar = np.full(m.ngeom, -1)
        self._geom_pillar[self.tip_geom] = np.arange(N_PILLARS)
        self.elliptic = params.cone == "elliptic"
        mujoco.mj_forward(m, self.data)
        self.start_pos = self.data.xpos[self.obj_body].copy()
        self.start_mat = self.data.xmat[self.obj_body].reshape(3, 3).copy()

    def _normal_forces(self) -> None:
        """The sensor's normal law as a joint force on each tip (compression = how far it is pushed down)."""
        d = self.data
        c_mm = -d.qpos[self.qpos_adr[:, 2]] * 1e3
        f = np.where(c_mm > 0, normal_force(c_mm, self.sensor), self.sensor.kn_a * c_mm)
        d.qfrc_applied[self.dof_adr[:, 2]] = f

    def _sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-pillar (sliding speed mm/s, 0 where not sliding; normal contact force; friction force magnitude) and
        the object's pose."""
        d, m = self.data, self.model
        slide = np.zeros(N_PILLARS)
        fn = np.zeros(N_PILLARS)
        ft = np.zeros(N_PILLARS)
        ncon = d.ncon
        if ncon:
            con = d.contact
            g = con.geom[:ncon]
            pillar = self._geom_pillar[g[:, 0]] + self._geom_pillar[g[:, 1]] + 1  # -1 unless one geom is a tip
            mine = (pillar >= 0) & ((g[:, 0] == self.obj_geom) | (g[:, 1] == self.obj_geom))
            mine &= con.efc_address[:ncon] >= 0
            if mine.any():
                k = np.flatnonzero(mine)
                i = pillar[k]
                if self.elliptic:  # the contact's forces in its own frame: normal, then the two friction axes
                    adr = con.efc_address[k]
                    f = np.stack([d.efc_force[adr], d.efc_force[adr + 1], d.efc_force[adr + 2]], 1)
                else:
                    f = np.zeros((len(k), 3))
                    cf = np.zeros(6)
                    for j, kk in enumerate(k):
                        mujoco.mj_contactForce(m, d, int(kk), cf)
                        f[j] = cf[:3]
                load = f[:, 0] > 0.0
                np.add.at(fn, i[load], f[load, 0])
                np.maximum.at(ft, i[load], np.hypot(f[load, 1], f[load, 2]))
                # Relative speed of the object's material point at the contact and the tip.
                obj_pos = d.xpos[self.obj_body]
                rot = d.xmat[self.obj_body].reshape(3, 3)
                v_lin = d.qvel[self.obj_dof: self.obj_dof + 3]
                w = rot @ d.qvel[self.obj_dof + 3: self.obj_dof + 6]  # free joint: angular velocity in the body frame
                r = con.pos[k] - obj_pos
                v_obj = v_lin + np.column_stack([w[1] * r[:, 2] - w[2] * r[:, 1], w[2] * r[:, 0] - w[0] * r[:, 2],
                                                 w[0] * r[:, 1] - w[1] * r[:, 0]])
                rel = v_obj - d.qvel[self.dof_adr[i]]
                normal = con.frame[k, :3]
                rel_t = rel - normal * np.sum(rel * normal, 1)[:, None]
                speed = np.sqrt(np.sum(rel_t**2, 1)) * 1e3
                fast = speed > self.params.slip_speed_mm_s
                # MuJoCo's friction is soft: a stuck contact yields elastically by a few micrometres, fast while its
                # force changes fast. A tip slides only when it moves with its friction force on the cone.
                on_cone = np.hypot(f[:, 1], f[:, 2]) >= self.params.cone_fraction * con.friction[k, 0] * f[:, 0]
                sliding = fast & load & on_cone
                np.maximum.at(slide, i[sliding], speed[sliding])
        pos = (d.xpos[self.obj_body] - self.start_pos) * 1e3
        r_rel = d.xmat[self.obj_body].reshape(3, 3) @ self.start_mat.T
        turn = np.degrees(np.arctan2(r_rel[1, 0], r_rel[0, 0]))
        return slide, fn, ft, np.array([pos[0], pos[1], turn])

    def run(self, grip_n: np.ndarray, accel_m_s2: np.ndarray, ext_force_n: np.ndarray,
            ext_torque_nm: np.ndarray) -> EngineOutput:
        """Advance over ``len(grip_n)`` samples; ``accel_m_s2``/``ext_force_n``/``ext_torque_nm`` are [N, 3]."""
        n = len(grip_n)
        d, m = self.data, self.model
        out = EngineOutput.allocate(n)
        speed = np.empty((n, N_PILLARS))
        xfrc = d.xfrc_applied[self.obj_body]
        for k in range(n):
            d.ctrl[0] = -float(grip_n[k])
            m.opt.gravity[:] = accel_m_s2[k]
            xfrc[:3] = ext_force_n[k]
            xfrc[3:] = ext_torque_nm[k]
            for _ in range(self.substeps):
                self._normal_forces()
                mujoco.mj_step(m, d)
            out.force[k], out.disp[k] = tip_readout(d.qpos[self.qpos_adr] * 1e3, self.sensor)
            speed[k], out.contact_fn[k], out.contact_ft[k], out.pose[k] = self._sample()
        out.slip = sustained_slides(speed, self.params.min_slide_mm, self.params.slide_gap_samples)
        return out


def tip_readout(q_mm: np.ndarray, sensor: SensorParams) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's forces and the deflections ([9, 3] each) from the tips' joint positions [9, 3] (mm): ``kt u``
    tangentially and the normal law of the compression (how far a tip is pushed down), as the sensor computes them."""
    c = np.maximum(-q_mm[:, 2], 0.0)
    disp = np.column_stack([q_mm[:, :2], c])
    force = np.column_stack([sensor.kt_n_mm * q_mm[:, :2], normal_force(c, sensor)])
    return force, disp


def sustained_slides(speed_mm_s: np.ndarray, min_slide_mm: float, gap: int) -> np.ndarray:
    """[N, 9] bool from [N, 9] sliding speeds (0 where a tip sticks): the episodes that carry a tip ``min_slide_mm``.

    Runs of sliding samples separated by at most ``gap`` samples form one episode (the gap counts as sliding);
    the distance is the speed integrated over the episode at the 1 kHz sample spacing.
    """
    out = np.zeros(speed_mm_s.shape, bool)
    for p in range(speed_mm_s.shape[1]):
        moving = np.flatnonzero(speed_mm_s[:, p] > 0)
        if not len(moving):
            continue
        breaks = np.flatnonzero(np.diff(moving) > gap + 1)
        starts = np.concatenate([[moving[0]], moving[breaks + 1]])
        ends = np.concatenate([moving[breaks], [moving[-1]]]) + 1
        for a, b in zip(starts, ends):
            if float(speed_mm_s[a:b, p].sum()) * DT_S >= min_slide_mm:
                out[a:b, p] = True
    return out
