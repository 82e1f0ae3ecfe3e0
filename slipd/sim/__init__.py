"""The PapillArray simulator: contact physics (``physics``), scenes (``scene``), effects (``effects``) and
data sets (``datasets``). Public entry points: ``load_scene``, ``parse_scene``, ``generate``, ``generate_batch``."""

from __future__ import annotations

from slipd.sim.scene import SceneError, generate, generate_batch, load_scene, parse_scene

__all__ = ["SceneError", "generate", "generate_batch", "load_scene", "parse_scene"]
