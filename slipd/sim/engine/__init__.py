"""The engine family: PapillArray grasps simulated on MuJoCo, physics written independently of ``slipd.sim.physics``.

``model`` writes the MJCF (nine compliant pillars, a jaw with a pad, the object), ``stepping`` runs it and reads out
the pillar forces, deflections, slip truth and the object's pose, ``spec`` is the scene file (``family: engine``,
``physics: {name: mujoco}``), ``generate`` turns a scene into a recording through the simulator's one sensor model
and label rule, and ``draws`` makes the ``engine`` data set's scenes. ``bullet`` runs the same scenes on a second
engine, Bullet (``physics: {name: bullet}``). Only ``stepping`` and ``generate`` import MuJoCo, and only ``bullet``
imports pybullet (both in the ``sim`` extra).
"""
