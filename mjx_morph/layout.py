"""The contract between the simulation (`mjx_morph.sim`) and the networks (`mjx_morph.nets`): one home for both.

A robot is seen by the policy as at most `NUM_TOKENS` tokens: token 0 is the torso, then the robot's limbs in the
MuJoCo body order of its own file, padded to 12. Each token carries `OBS_DIM` proprioceptive features and drives
`ACTS_PER_TOKEN` joint slots; action entry `2 t + k` is token t's joint slot k (0 = x, 1 = y).

Per-token feature layout (the 52 columns of `Obs.proprio`):

    0-2   body_xpos (x relative to the torso)   3-5   body_xvelp   6-8   body_xvelr   9-12  body_xquat
    13-15 body_pos   16-18 body_ipos   19-22 body_iquat   23-26 geom_quat   27 body_mass   28-29 body_shape
    30-40 joint slot 0: qpos (scaled to [0, 1] over the range), qvel, jnt_pos 3, jnt_range 2, jnt_axis 3, gear
    41-51 joint slot 1: the same

The 17 time-varying columns (`STATE_FEATURES`) are 0-12, 30, 31, 41, 42; the other 35 are the static features
whose normalised values form the per-token context (`Robots.context`, `CTX_DIM` columns, grouped by
`CONTEXT_GROUPS`).
"""
from __future__ import annotations

from typing import Iterable, NamedTuple

import jax
import numpy as np

from .unimal.morphology import MAX_NODES

NUM_TOKENS = MAX_NODES                        # 12: torso + up to 10 limbs, padded (MetaMorph's MAX_LIMBS)
OBS_DIM = 52                                  # proprioceptive features per token
CTX_DIM = 35                                  # context features per token
ACTS_PER_TOKEN = 2                            # joint slots per token
NUM_ACTIONS = NUM_TOKENS * ACTS_PER_TOKEN     # 24
HFIELD_DIM = 1410                             # height-map samples of csr / obstacle (47 rows x 30 columns)

#: the time-varying columns of the 52: body_xpos, xvelp, xvelr, xquat (0-12), slot 0 qpos, qvel, slot 1 qpos, qvel
STATE_FEATURES = np.array([*range(13), 30, 31, 41, 42], dtype=np.int32)
STATE_DIM = len(STATE_FEATURES)               # 17


class Robots(NamedTuple):
    """Per-robot constants of the policy, robot axis first (R robots)."""
    context: jax.Array     # (R, 12, 35) float32, normalised with ModuMorph's fixed bounds; padded tokens 0
    node_mask: jax.Array   # (R, 12) bool, True = real token (torso + limbs)
    act_mask: jax.Array    # (R, 24) bool, True = real actuator


class Obs(NamedTuple):
    """One observation per env (any leading batch shape)."""
    proprio: jax.Array                # (..., 12, 52) float32; raw from the env, normalised by the learner
    prev_action: jax.Array            # (..., 24) float32, the executed (masked, clamped) previous action
    robot: jax.Array                  # (...) int32, row of `Robots`
    hfield: jax.Array | None = None   # (..., 1410) float32 for csr / obstacle, (..., 0) for ft / incline


# ---- context feature groups ------------------------------------------------------------------------------------
_LIMB_GROUPS = (("body_pos", 3), ("body_ipos", 3), ("body_iquat", 4), ("geom_quat", 4), ("body_mass", 1),
                ("body_shape", 2))
_JOINT_GROUPS = (("jnt_pos", 3), ("joint_range", 2), ("joint_axis", 3), ("gear", 1))


def _groups() -> dict[str, tuple[int, ...]]:
    cols: dict[str, list[int]] = {}
    i = 0
    for name, n in _LIMB_GROUPS:
        cols[name] = list(range(i, i + n))
        i += n
    for _slot in range(ACTS_PER_TOKEN):
        for name, n in _JOINT_GROUPS:
            cols.setdefault(name, []).extend(range(i, i + n))
            i += n
    assert i == CTX_DIM
    return {k: tuple(v) for k, v in cols.items()}


#: context columns of each named feature group: the limb's 17 (body_pos ... body_shape), then per joint slot 9
CONTEXT_GROUPS: dict[str, tuple[int, ...]] = _groups()


def context_mask(keep: Iterable[str] | None) -> np.ndarray:
    """(35,) float32: 1 on the columns of the kept feature groups (all when `keep` is None).

    A masked feature is set to 0 on every token of every robot: the middle of its [-1, 1] normalisation range, the
    same value for all robots, so it carries no information about the body (single-context-feature studies)."""
    if keep is None:
        return np.ones(CTX_DIM, np.float32)
    keep = list(keep)
    unknown = [k for k in keep if k not in CONTEXT_GROUPS]
    if unknown:
        raise ValueError(f"context_features: unknown feature(s) {unknown}; expected some of {list(CONTEXT_GROUPS)}")
    m = np.zeros(CTX_DIM, np.float32)
    for k in keep:
        m[list(CONTEXT_GROUPS[k])] = 1.0
    return m
