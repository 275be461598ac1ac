"""Generate new UNIMAL robots from scratch (DERL's population init): `generate_robot` and `generate_set`.

The design space is in `design_space`, the working copy and its checks in `draft`, the operators in `mutations`.

Decisions where DERL leaves room (ours):
- Population init: one `grow_limb`, then random operators (`random_op`) until the robot has >= target limbs.
  DERL draws the target from {2..8}; our default `DEFAULT_NUM_LIMBS` = (6, 10) gives limb counts comparable to
  the original train set (4-10 limbs, mean 8.1, mode 8; generated with the height cap below: 6-10, mean 7.9; a
  pair can overshoot the target by one).
- Height cap (a selection of ours, like evolution's): unselected random robots are taller than the evolved
  originals (measured on 100: standing height 0.55-2.45 m, median 1.14, tree depth 2-6; originals 0.30-1.04 m,
  depth 2-5), so by default a robot whose standing height exceeds `DEFAULT_MAX_HEIGHT` = 1.05 m is drawn again
  (about 40 % are kept). This keeps the depth at 2-5, and slightly favours smaller robots (mean 7.9 limbs with the
  cap, 8.5 without). `max_height=None` gives DERL's unselected distribution.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from .design_space import DENSITIES, topology_key
from .draft import Draft
from .errors import RobotError
from .morphology import MAX_LIMBS, TORSO_RADIUS, Morphology
from .mutations import apply, as_rng, pick, random_op

DEFAULT_NUM_LIMBS = (6, 10)        # target limb count drawn uniformly from this closed range
DEFAULT_MAX_HEIGHT = 1.05          # standing height cap (m); None = no cap
MAX_OPS = 2000                     # random operators per robot before starting again


def generate_robot(rng_or_seed, name: str, num_limbs: tuple[int, int] = DEFAULT_NUM_LIMBS,
                   max_height: float | None = DEFAULT_MAX_HEIGHT, max_ops: int = MAX_OPS) -> Morphology:
    """One new robot (DERL population init): draw densities and a target limb count uniformly from the closed
    range `num_limbs`, grow one limb, then apply random mutation operators until the robot has at least that many
    limbs. A robot taller than `max_height` (standing height, m; None = no cap) is drawn again from the same
    stream. `rng_or_seed` is a `numpy.random.Generator` or anything `numpy.random.default_rng` accepts."""
    lo, hi = num_limbs
    if not 1 <= lo <= hi <= MAX_LIMBS:
        raise ValueError(f"num_limbs={num_limbs}: expected 1 <= lo <= hi <= {MAX_LIMBS}")
    rng = as_rng(rng_or_seed)
    for _ in range(100):
        d = Draft(name, 0.0, pick(rng, DENSITIES), TORSO_RADIUS, pick(rng, DENSITIES), [], [])
        target = int(rng.integers(lo, hi + 1))
        for _ in range(max_ops):
            if len(d.nodes) >= target:
                break
            apply(d, random_op(d, rng), rng)
        else:
            continue
        if max_height is None or d.height <= max_height + 1e-9:
            return d.to_morphology()
    raise RobotError(name, "", f"could not grow a robot with {num_limbs} limbs and height <= {max_height}")


def generate_set(num: int, seed: int, *, num_limbs: tuple[int, int] = DEFAULT_NUM_LIMBS,
                 max_height: float | None = DEFAULT_MAX_HEIGHT,
                 exclude_topologies: Iterable[str] | None = None, prefix: str = "gen") -> list[Morphology]:
    """`num` robots named `<prefix>-<seed>-<index>`. Robot `index` is drawn from `default_rng([seed, index, a])`
    for a = 0, 1, ... until its `topology_key` is not in `exclude_topologies`, so a robot does not depend on
    the others and the same arguments always give the same robots."""
    exclude = set(exclude_topologies or ())
    out = []
    for index in range(num):
        for attempt in range(10_000):
            m = generate_robot(np.random.default_rng([seed, index, attempt]), f"{prefix}-{seed}-{index}", num_limbs,
                               max_height)
            if topology_key(m) not in exclude:
                break
        else:
            raise RobotError(f"{prefix}-{seed}-{index}", "", "every topology drawn is excluded")
        out.append(m)
    return out
