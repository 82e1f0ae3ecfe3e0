"""PapillArray geometry in Contactile SDK order (centre pillar P4).

Pillar i sits at x = 7 (1 - i mod 3) mm, y = 7 (1 - i div 3) mm. Every module of slipd uses this
numbering; a model manifest lists which pillars feed the model and in which order.
"""

from __future__ import annotations

import numpy as np

N_PILLARS = 9
PITCH_MM = 7.0
CENTRE = 4
CORNERS = (0, 2, 6, 8)
EDGES = (1, 3, 5, 7)
OUTER = (0, 1, 2, 3, 5, 6, 7, 8)
"""The eight outer pillars in SDK raster order: the order the authors' released models expect."""

CHANNELS = ("fx", "fy", "fz")

_idx = np.arange(N_PILLARS)
PILLAR_XY_MM = np.stack(
    [PITCH_MM * (1 - _idx % 3), PITCH_MM * (1 - _idx // 3)], axis=1
).astype(np.float64)
"""[9, 2] pillar base positions (mm) in the sensor frame."""

HEIGHT_OFFSET_MM = np.array([0.5, 0.2, 0.5, 0.2, 0.0, 0.2, 0.5, 0.2, 0.5])
"""How far each unloaded tip sits below the centre pillar's tip (corners 0.5, edges 0.2 mm)."""

# Sensor ranges (PTS v2.1 spec): the real sensor saturates beyond these.
FT_RANGE_N = 4.0
FZ_RANGE_N = 15.0
CONTACT_THRESHOLD_N = 0.5
"""SDK contact flag: a pillar is in contact when its normal force exceeds this."""
