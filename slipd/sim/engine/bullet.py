"""The second engine: the same grasps on Bullet (pybullet), a physics code base independent of MuJoCo and of ours.

Why a second engine: a detector trained on one engine's recordings and tested on another's measures how far it
generalises across physics nobody here wrote, which holding out one family of our own simulator cannot.

Bullet differs from MuJoCo where it matters for slip: its contacts are rigid constraints solved by sequential
impulses (projected Gauss-Seidel) with a box friction cone (each of two friction directions clamped to mu x normal),
split-impulse penetration recovery and Featherstone multibodies for the jointed parts; MuJoCo's are soft
constraints on an elliptic cone solved by Newton's method.

Units: Bullet's tolerances assume bodies of centimetres to metres, and the pillar tips are a millimetre across, so
the world is built in millimetres (``L``: 1 unit = 1 mm) with kilograms and seconds; a force unit is then 1 mN.

* Nine pillar tips, each at the end of a chain of three prismatic joints (x, y, z) on the fixed finger. The
  tangential joints are springs of the sensor's tangential stiffness and the normal joint follows the sensor's
  normal law, both applied as joint forces before every step (Bullet's joints have no springs).
* The jaw: a plate on a prismatic joint along z, pushed towards the sensor by the grip force, carrying a pad on
  two tangential springs (the jaw's rubber pad).
* The object: a free body (box, cylinder across or along the finger, sphere, or a box whose edge lies over the
  array). The grasp's acceleration field, the pushes and the twists act on it alone as external forces (the
  finger and jaw are held by the arm).
"""

from __future__ import annotations

import numpy as np
import pybullet as pb

from slipd.geometry import HEIGHT_OFFSET_MM, N_PILLARS, PILLAR_XY_MM
from slipd.sim.engine.model import START_GAP_MM, BulletParams, ObjectGeometry, object_half_height_mm
from slipd.sim.engine.stepping import EngineOutput, sustained_slides, tip_readout
from slipd.sim.physics import DT_S, SensorParams, normal_force

F = 1e3
"""Newtons -> the world's force unit (kg mm / s^2 = 1 mN)."""
TIP_MASS_KG = 0.002
TIP_RADIUS_MM = 1.0
SLIDER_MASS_KG = 1e-4
"""The two intermediate links of each tip's x-y-z chain (no collision)."""
TIP_DAMPING_N_S_M = 2.0
JAW_MASS_KG = 0.05
JAW_DAMPING_N_S_M = 30.0
PAD_MASS_KG = 0.005
PAD_DAMPING_N_S_M = 5.0
MAX_SPEED = 1e6
"""Joint speed cap (mm/s): Bullet caps multibody joints at 100 units/s by default, which in millimetres would hold
back a tip's spring."""


def _shape(client: int, obj: ObjectGeometry) -> tuple[int, tuple[float, float, float], tuple[float, ...]]:
    """The object's collision shape, its start position (mm) and orientation."""
    h = object_half_height_mm(obj)
    z = h + START_GAP_MM
    q = (0.0, 0.0, 0.0, 1.0)
    if obj.shape in ("box", "edge"):
        s = obj.size_mm / 2
        cid = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[s, s, h], physicsClientId=client)
        x = obj.edge_mm + s if obj.shape == "edge" else 0.0
        return cid, (x, 0.0, z), q
    if obj.shape == "sphere":
        return pb.createCollisionShape(pb.GEOM_SPHERE, radius=h, physicsClientId=client), (0.0, 0.0, z), q
    cid = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=h, height=obj.size_mm, physicsClientId=client)
    # The cylinder's axis is its local z: turned onto the sensor's x (across) or y (along).
    axis = (0.0, 1.0, 0.0) if obj.shape == "cylinder_across" else (1.0, 0.0, 0.0)
    q = tuple(pb.getQuaternionFromAxisAngle(axis, np.pi / 2))
    return cid, (0.0, 0.0, z), q


class BulletSim:
    """One scene's Bullet world; ``run`` advances it over input profiles (as ``stepping.EngineSim`` does)."""

    def __init__(self, sensor: SensorParams, obj: ObjectGeometry, params: BulletParams) -> None:
        self.sensor, self.obj, self.params = sensor, obj, params
        c = self.client = pb.connect(pb.DIRECT)
        pb.setGravity(0, 0, 0, physicsClientId=c)
        self.substeps = max(1, round(DT_S / (params.timestep_ms * 1e-3)))
        # Contacts are kept while their gap is under 0.05 mm (the default, 0.02 units, was meant for metres), and
        # the friction cone is Bullet's own box (two clamped directions), not its optional cone approximation.
        pb.setPhysicsEngineParameter(fixedTimeStep=DT_S / self.substeps, numSolverIterations=params.solver_iterations,
                                     erp=params.erp, contactERP=params.erp, frictionERP=params.erp,
                                     contactBreakingThreshold=0.05, enableConeFriction=0,
                                     physicsClientId=c)
        self._build_finger(obj)
        self._build_jaw(obj)
        cid, pos, orn = _shape(c, obj)
        pos = (pos[0] + obj.offset_mm[0], pos[1] + obj.offset_mm[1], pos[2])
        self.object = pb.createMultiBody(obj.mass_kg, cid, -1, pos, orn, physicsClientId=c)
        pb.changeDynamics(self.object, -1, lateralFriction=1.0, linearDamping=0.0, angularDamping=0.0,
                          physicsClientId=c)
        self.start_pos = np.array(pos)
        self.start_orn = np.array(orn)

    def _build_finger(self, obj: ObjectGeometry) -> None:
        c = self.client
        tip = pb.createCollisionShape(pb.GEOM_SPHERE, radius=TIP_RADIUS_MM, physicsClientId=c)
        masses, shapes, pos, parents, jtypes, axes = [], [], [], [], [], []
        for i in range(N_PILLARS):
            x, y = PILLAR_XY_MM[i]
            zc = -HEIGHT_OFFSET_MM[i] - TIP_RADIUS_MM
            base = len(masses)
            for a, axis in enumerate(((1, 0, 0), (0, 1, 0), (0, 0, 1))):
                last = a == 2
                masses.append(TIP_MASS_KG if last else SLIDER_MASS_KG)
                shapes.append(tip if last else -1)
                pos.append((x, y, zc) if a == 0 else (0.0, 0.0, 0.0))
                parents.append(0 if a == 0 else base + a)  # link indices are 1-based in createMultiBody
                jtypes.append(pb.JOINT_PRISMATIC)
                axes.append(axis)
        n = len(masses)
        self.finger = pb.createMultiBody(
            0.0, -1, -1, (0, 0, 0), (0, 0, 0, 1), linkMasses=masses, linkCollisionShapeIndices=shapes,
            linkVisualShapeIndices=[-1] * n, linkPositions=pos, linkOrientations=[(0, 0, 0, 1)] * n,
            linkInertialFramePositions=[(0, 0, 0)] * n, linkInertialFrameOrientations=[(0, 0, 0, 1)] * n,
            linkParentIndices=parents, linkJointTypes=jtypes, linkJointAxis=axes, useMaximalCoordinates=0,
            physicsClientId=c)
        self.joints = list(range(n))
        pb.setJointMotorControlArray(self.finger, self.joints, pb.VELOCITY_CONTROL, forces=[0.0] * n,
                                     physicsClientId=c)
        for j in range(n):
            pb.changeDynamics(self.finger, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                              maxJointVelocity=MAX_SPEED, physicsClientId=c)
        self.tip_link = np.arange(N_PILLARS) * 3 + 2
        for i in range(N_PILLARS):
            pb.changeDynamics(self.finger, int(self.tip_link[i]), lateralFriction=obj.mu, physicsClientId=c)
        self._link_pillar = np.full(n, -1)
        self._link_pillar[self.tip_link] = np.arange(N_PILLARS)

    def _build_jaw(self, obj: ObjectGeometry) -> None:
        c = self.client
        top = object_half_height_mm(obj) * 2 + START_GAP_MM
        plate = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[30.0, 30.0, 0.5], physicsClientId=c)
        # Base fixed; link 0 the jaw on z, links 1-2 the pad on x and y (the pad collides with the object).
        self.jaw = pb.createMultiBody(
            0.0, -1, -1, (0, 0, top + 0.5 + 1.0), (0, 0, 0, 1),
            linkMasses=[JAW_MASS_KG, 1e-4, PAD_MASS_KG], linkCollisionShapeIndices=[-1, -1, plate],
            linkVisualShapeIndices=[-1] * 3, linkPositions=[(0, 0, 0)] * 3, linkOrientations=[(0, 0, 0, 1)] * 3,
            linkInertialFramePositions=[(0, 0, 0)] * 3, linkInertialFrameOrientations=[(0, 0, 0, 1)] * 3,
            linkParentIndices=[0, 1, 2], linkJointTypes=[pb.JOINT_PRISMATIC] * 3,
            linkJointAxis=[(0, 0, 1), (1, 0, 0), (0, 1, 0)], physicsClientId=c)
        pb.setJointMotorControlArray(self.jaw, [0, 1, 2], pb.VELOCITY_CONTROL, forces=[0.0] * 3, physicsClientId=c)
        pb.changeDynamics(self.jaw, 2, lateralFriction=obj.jaw_mu, physicsClientId=c)
        for j in range(3):
            pb.changeDynamics(self.jaw, j, linearDamping=0.0, angularDamping=0.0, maxJointVelocity=MAX_SPEED,
                              physicsClientId=c)

    def close(self) -> None:
        pb.disconnect(self.client)

    def _joint_forces(self, q: np.ndarray, v: np.ndarray, grip_n: float, jq: np.ndarray, jv: np.ndarray) -> None:
        """Springs and dampers of the tips and the pad, the sensor's normal law, the grip (world units)."""
        s = self.sensor
        k = s.kt_n_mm * F  # mN per mm
        qq, vv = q.reshape(N_PILLARS, 3), v.reshape(N_PILLARS, 3)
        f = np.empty((N_PILLARS, 3))
        f[:, :2] = -k * qq[:, :2]
        comp = np.maximum(-qq[:, 2], 0.0)
        f[:, 2] = np.where(qq[:, 2] < 0, normal_force(comp, s) * F, -s.kn_a * F * qq[:, 2])
        f -= TIP_DAMPING_N_S_M * vv  # N s/m = kg/s: the same in mm units
        pb.setJointMotorControlArray(self.finger, self.joints, pb.TORQUE_CONTROL, forces=f.ravel().tolist(),
                                     physicsClientId=self.client)
        kp = self.obj.jaw_kt_n_mm * F
        jaw = [-grip_n * F - JAW_DAMPING_N_S_M * jv[0],
               -kp * jq[1] - PAD_DAMPING_N_S_M * jv[1], -kp * jq[2] - PAD_DAMPING_N_S_M * jv[2]]
        pb.setJointMotorControlArray(self.jaw, [0, 1, 2], pb.TORQUE_CONTROL, forces=jaw, physicsClientId=self.client)

    def _states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        c = self.client
        fs = pb.getJointStates(self.finger, self.joints, physicsClientId=c)
        js = pb.getJointStates(self.jaw, [0, 1, 2], physicsClientId=c)
        return (np.array([s[0] for s in fs]), np.array([s[1] for s in fs]), np.array([s[0] for s in js]),
                np.array([s[1] for s in js]))

    def _sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-pillar (sliding speed mm/s, 0 where not sliding; normal contact force N; friction force N) and the
        object's pose (x, y mm from its start; turn about the sensor normal, deg)."""
        c = self.client
        slide = np.zeros(N_PILLARS)
        fn = np.zeros(N_PILLARS)
        ft = np.zeros(N_PILLARS)
        pos, orn = pb.getBasePositionAndOrientation(self.object, physicsClientId=c)
        v_lin, w = pb.getBaseVelocity(self.object, physicsClientId=c)
        pos, v_lin, w = np.array(pos), np.array(v_lin), np.array(w)
        contacts = pb.getContactPoints(self.object, self.finger, physicsClientId=c)
        if contacts:
            links = sorted({int(ct[4]) for ct in contacts})
            states = pb.getLinkStates(self.finger, links, computeLinkVelocity=1, physicsClientId=c)
            tip_v = {lk: np.array(st[6]) for lk, st in zip(links, states)}
            for ct in contacts:
                i = self._link_pillar[int(ct[4])]
                if i < 0:
                    continue
                n, f1, f2 = ct[9] / F, ct[10] / F, ct[12] / F
                if n <= 0.0:
                    continue
                fn[i] += n
                ftan = float(np.hypot(f1, f2))
                ft[i] = max(ft[i], ftan)
                p = np.array(ct[5])  # on the object
                normal = np.array(ct[7])
                rel = v_lin + np.cross(w, p - pos) - tip_v[int(ct[4])]
                rel_t = rel - normal * float(rel @ normal)
                speed = float(np.sqrt(rel_t @ rel_t))
                # Bullet's cone is a box: a direction at its clamp is on the cone.
                on_cone = max(abs(f1), abs(f2), ftan) >= self.params.cone_fraction * self.obj.mu * n
                if speed > self.params.slip_speed_mm_s and on_cone:
                    slide[i] = max(slide[i], speed)
        r_rel = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3) @ \
            np.array(pb.getMatrixFromQuaternion(self.start_orn.tolist())).reshape(3, 3).T
        turn = np.degrees(np.arctan2(r_rel[1, 0], r_rel[0, 0]))
        d = pos - self.start_pos
        return slide, fn, ft, np.array([d[0], d[1], turn])

    def run(self, grip_n: np.ndarray, accel_m_s2: np.ndarray, ext_force_n: np.ndarray,
            ext_torque_nm: np.ndarray) -> EngineOutput:
        """Advance over ``len(grip_n)`` samples; ``accel_m_s2``/``ext_force_n``/``ext_torque_nm`` are [N, 3]."""
        n = len(grip_n)
        c = self.client
        out = EngineOutput.allocate(n)
        speed = np.empty((n, N_PILLARS))
        m = self.obj.mass_kg
        for k in range(n):
            load = (m * np.asarray(accel_m_s2[k]) + np.asarray(ext_force_n[k])) * F  # N -> mN
            torque = np.asarray(ext_torque_nm[k]) * F * 1e3  # N m -> mN mm
            for _ in range(self.substeps):
                q, v, jq, jv = self._states()
                self._joint_forces(q, v, float(grip_n[k]), jq, jv)
                pos, _ = pb.getBasePositionAndOrientation(self.object, physicsClientId=c)
                pb.applyExternalForce(self.object, -1, load.tolist(), pos, pb.WORLD_FRAME, physicsClientId=c)
                pb.applyExternalTorque(self.object, -1, torque.tolist(), pb.WORLD_FRAME, physicsClientId=c)
                pb.stepSimulation(physicsClientId=c)
            q, _, _, _ = self._states()
            out.force[k], out.disp[k] = tip_readout(q.reshape(N_PILLARS, 3), self.sensor)
            speed[k], out.contact_fn[k], out.contact_ft[k], out.pose[k] = self._sample()
        out.slip = sustained_slides(speed, self.params.min_slide_mm, self.params.slide_gap_samples)
        return out
