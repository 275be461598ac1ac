"""Reward and termination of one control step, as MetaMorph computes them.

reward = FORWARD_REWARD_WEIGHT * (x_torso(t+1) - x_torso(t)) / 0.02 [/ cos(10 deg) on the incline]
         - CTRL_COST_WEIGHT * sum(a^2)    (weight 0 in MetaMorph/ModuMorph; a = the raw policy action, real entries)
x_torso is the world x of `torso/0` as MuJoCo's data holds it after the step (see observation.py: kinematics of the
start of the last substep, as MetaMorph reads it).

Terminations: fall when torso_height = round(z_torso - ground(x, y), 3) <= (z0 - 0.2) * STAND_HEIGHT_RATIO (both
heights in the simulation's frame, `Terrain.origin`);
|y_torso| >= 19 for incline, csr and obstacle; the 1000-step limit is a truncation, not a terminal.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .tasks import CONTROL_DT, Task
from .terrain import Terrain


class Outcome(NamedTuple):
    reward: jax.Array
    fell: jax.Array
    out_of_bounds: jax.Array
    torso_height: jax.Array


def evaluate(task: Task, terrain: Terrain, terrain_state, x_before, torso_pos, orig_height, raw_action,
             act_mask) -> Outcome:
    """The outcome of a step that moved the torso from x = `x_before` to `torso_pos` (the env's terrain object and
    the episode's terrain state give the ground under it)."""
    x, y, z = torso_pos[0], torso_pos[1], torso_pos[2]
    speed = (x - x_before) / CONTROL_DT
    if task.incline_deg:
        speed = speed / np.cos(np.radians(task.incline_deg))
    reward = task.forward_weight * speed
    if task.ctrl_cost_weight:
        reward = reward - task.ctrl_cost_weight * jnp.sum(jnp.where(act_mask, raw_action, 0.0) ** 2)
    ground = terrain.ground_height(terrain_state, x, y)
    height = jnp.round(z - ground, 3)
    fell = height <= orig_height * task.stand_ratio
    oob = jnp.abs(y) >= task.side_limit if task.side_limit is not None else jnp.asarray(False)
    return Outcome(reward=reward.astype(jnp.float32), fell=fell, out_of_bounds=oob, torso_height=height)
