"""The four UNIMAL tasks, each one record (`Task`) holding every fact of the task in one place.

| task     | terrain (physics)                            | stand ratio | side limit   | height map | decoder  | return range |
|----------|----------------------------------------------|-------------|--------------|------------|----------|--------------|
| ft       | plane, top z = 1 (0 simulated, terrain/)     | 0.5         | none         | no         | []       | 52 / 5008    |
| incline  | plane tilted -10 deg about y (uphill +x)     | 0.2         | abs(y) >= 19 | no         | []       | -74 / 3751   |
| csr      | per-episode corridor, height-field patch     | 0.3         | abs(y) >= 19 | yes        | [64]     | 71 / 3000    |
| obstacle | floor + walls + 50 boxes, height-field patch | 0.5         | abs(y) >= 19 | yes        | [64, 64] | 126 / 2403   |

Reward: forward_weight * torso x-velocity (along the slope on the incline) - ctrl_cost_weight * sum(a^2) (`reward.py`).
The decoder column is the hidden layers of the policy's per-limb decoder for the task (MetaMorph / ModuMorph task
configs); the return range is the paper's per-task range of returns over robots, used to normalise returns
((R - lo) / (hi - lo)) in evaluations and reports.

Deviations from the original worlds (listed in `mjx_morph/sim/__init__.py`):
- ft: the 200 m x 200 m floor box is an infinite plane at z = 1 (the same surface wherever a robot can get in 20 s).
- incline: the 150 m x 40 m tilted slab is an infinite tilted plane through the slab's top face; the slab's ends
  are out of reach in 20 s and its sides are beyond the side limit.
- csr and obstacle: see `terrain/` (one moving height-field patch instead of boxes and per-segment height
  fields; obstacles are height-field columns standing on the floor instead of boxes floating 0.1 m above it).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .terrain import KINDS as TERRAIN_KINDS

CONTROL_DT = 0.02
FRAME_SKIP = 4
EPISODE_LENGTH = 1000
FLOOR_OFFSET = 0.2       # TERRAIN.FLOOR_OFFSET: orig_height = z0 - 0.2
RESET_NOISE = 0.005      # ENV.RESET_NOISE_SCALE


@dataclasses.dataclass(frozen=True)
class Task:
    name: str
    terrain: str                   # "plane", "incline", "corridor", "obstacles" (a kind of `terrain.KINDS`)
    stand_ratio: float             # ENV.STAND_HEIGHT_RATIO
    side_limit: float | None       # terminate when |y_torso| >= side_limit
    hfield_obs: bool               # the 1410-value height map is part of the observation
    decoder_dims: tuple[int, ...]  # hidden layers of the policy's per-limb decoder for this task
    return_range: tuple[float, float]   # the paper's (min, max) return over robots (normalised returns)
    incline_deg: float = 0.0       # TERRAIN.INCLINE_ANGLE magnitude (uphill along +x)
    forward_weight: float = 1.0    # ENV.FORWARD_REWARD_WEIGHT
    ctrl_cost_weight: float = 0.0  # ENV.CTRL_COST_WEIGHT

    def normalised(self, ret):
        """(R - min) / (max - min) with the task's return range (float64 numpy)."""
        lo, hi = self.return_range
        return (np.asarray(ret, np.float64) - lo) / (hi - lo)

    @property
    def uses_hfield(self) -> bool:
        """The physics of the task's terrain is the moving height-field patch (`terrain.HeightField`)."""
        return TERRAIN_KINDS[self.terrain].uses_hfield


TASKS = {
    "ft": Task("ft", "plane", 0.5, None, False, (), (52.0, 5008.0)),
    "incline": Task("incline", "incline", 0.2, 19.0, False, (), (-74.0, 3751.0), incline_deg=10.0),
    "csr": Task("csr", "corridor", 0.3, 19.0, True, (64,), (71.0, 3000.0)),
    "obstacle": Task("obstacle", "obstacles", 0.5, 19.0, True, (64, 64), (126.0, 2403.0)),
}


def get_task(name: str | Task) -> Task:
    if isinstance(name, Task):
        return name
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; expected one of {', '.join(TASKS)}")
    return TASKS[name]
