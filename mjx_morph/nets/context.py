"""The 35 per-limb context features by name, and masking them (single-context-feature studies).

Columns of `Robots.context` (spec/architecture.md, "Per-limb context"): body_pos 3, body_ipos 3, body_iquat 4,
geom_quat 4, body_mass 1, body_shape 2, then per joint slot (2 slots) jnt_pos 3, joint_range 2, joint_axis 3, gear 1.
A masked feature is set to 0 on every limb of every robot: the middle of its [-1, 1] normalisation range, the same
value for all robots, so it carries no information about the body.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

_LIMB = (("body_pos", 3), ("body_ipos", 3), ("body_iquat", 4), ("geom_quat", 4), ("body_mass", 1),
         ("body_shape", 2))
_JOINT = (("jnt_pos", 3), ("joint_range", 2), ("joint_axis", 3), ("gear", 1))


def _groups() -> dict[str, tuple[int, ...]]:
    cols: dict[str, list[int]] = {}
    i = 0
    for name, n in _LIMB:
        cols[name] = list(range(i, i + n))
        i += n
    for _slot in range(2):
        for name, n in _JOINT:
            cols.setdefault(name, []).extend(range(i, i + n))
            i += n
    assert i == 35
    return {k: tuple(v) for k, v in cols.items()}


CONTEXT_GROUPS: dict[str, tuple[int, ...]] = _groups()


def context_mask(keep: Iterable[str] | None) -> np.ndarray:
    """(35,) float32: 1 on the columns of the kept feature groups (all when `keep` is None)."""
    if keep is None:
        return np.ones(35, np.float32)
    keep = list(keep)
    unknown = [k for k in keep if k not in CONTEXT_GROUPS]
    if unknown:
        raise ValueError(f"context_features: unknown feature(s) {unknown}; expected some of {list(CONTEXT_GROUPS)}")
    m = np.zeros(35, np.float32)
    for k in keep:
        m[list(CONTEXT_GROUPS[k])] = 1.0
    return m


def mask_context(robots, keep: Iterable[str] | None):
    """`robots` (a Robots tuple) with every context feature outside `keep` set to 0."""
    if keep is None:
        return robots
    return robots._replace(context=robots.context * context_mask(keep))
