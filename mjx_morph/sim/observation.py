"""Per-token proprioceptive observation (12 x 52) from an MJX state, exactly as MetaMorph builds it.

Token t = 0 is the torso, then the robot's limbs in the MuJoCo body order of its own file, zero rows for padding.
Per token (indices into the 52):
  0-2   body_xpos (x replaced by x - x_torso; y, z in MetaMorph's world)      3-5   body_xvelp     6-8  body_xvelr     9-12  body_xquat
  13-15 body_pos   16-18 body_ipos   19-22 body_iquat   23-26 geom_quat   27 body_mass   28-29 body_shape
  30-40 joint slot 0 (x): qpos (scaled to [0, 1] over the range), qvel, jnt_pos 3, jnt_range 2, jnt_axis 3, gear
  41-51 joint slot 1 (y): the same
The 17 time-varying entries are 0-12, 30, 31, 41, 42; the other 35 are the raw static features, precomputed per
robot (`model.Tables.static_feat`) and added here. body_xvelp/xvelr are mujoco-py's `body_xvelp/xvelr`, which
MetaMorph reads: `mj_jacBody(body) @ qvel`, the world-frame velocity of the body *origin* (= MuJoCo's
`mj_objectVelocity` of mjOBJ_XBODY, not of mjOBJ_BODY, the centre of mass, which mujoco-py does not use).

Which kinematics: like MetaMorph (mujoco-py reads `sim.data` after `mj_step`), positions and orientations of bodies
are those MuJoCo computed at the start of the last physics substep, while qpos/qvel are the current ones. Body
velocities are mujoco-py's `body_xvelp/xvelr` read after the step: the Jacobian of the start of the last substep
(`cdof`, `xpos`, `subtree_com`) times the *current* qvel, i.e. the new velocities (not `cvel`, which MuJoCo
computed from the qvel before the last integration). `body_velocity` builds that spatial velocity, `cvel` with the
current qvel: sum over the dofs of the body and its ancestors of cdof * qvel. After a reset the kinematics are
recomputed from the reset state (MetaMorph's `set_state` calls `mj_forward`), where both agree.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..layout import OBS_DIM


def ancestor_dofs(mm) -> np.ndarray:
    """(nbody, nv) float32: 1 where dof j moves body b (j belongs to b or to an ancestor of b). Static: every
    robot of a set shares the tree."""
    out = np.zeros((mm.nbody, mm.nv), np.float32)
    for b in range(mm.nbody):
        a = b
        while True:
            out[b, mm.dof_bodyid == a] = 1.0
            if a == 0:
                break
            a = mm.body_parentid[a]
    return out


def body_velocity(ancestors: jax.Array, cdof: jax.Array, qvel: jax.Array) -> jax.Array:
    """(nbody, 6) spatial velocity in MuJoCo's `cvel` layout (angular, linear at the root's subtree com) from the
    Jacobian `cdof` (nv, 6) and `qvel`: what `mj_comVel` gives for this qvel."""
    return ancestors @ (cdof * qvel[:, None])


def object_velocity(cvel: jax.Array, xpos: jax.Array, subtree_com: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(linear, angular) world-frame velocity of body origins from `cvel` at the root subtree com."""
    ang = cvel[..., :3]
    lin = cvel[..., 3:] - jnp.cross(xpos - subtree_com, ang)
    return lin, ang


def proprio(xpos, xquat, cvel, subtree_com, qpos, qvel, tab, node_mask, act_mask,
            origin=(0.0, 0.0, 0.0)) -> jax.Array:
    """(12, 52) float32 observation of one env. Arrays are one env's MJX data, `cvel` from `body_velocity` with the
    current qvel; `tab` one robot's `Tables` row. All robot bodies hang from the torso (body 1), so the root
    subtree com is `subtree_com[1]`. `origin`: MetaMorph's coordinates of the simulation's origin (the terrain's),
    added to the observed y and z so that they are MetaMorph's."""
    b = tab.body_of_token
    p = xpos[b]
    p = p.at[:, 0].add(-xpos[1, 0]).at[:, 1].add(origin[1]).at[:, 2].add(origin[2])
    lin, ang = object_velocity(cvel[b], xpos[b], subtree_com[1])
    q = (qpos[tab.qadr_of_action] - tab.jnt_lo) / tab.jnt_span
    v = qvel[tab.vadr_of_action]
    dyn = jnp.concatenate([p, lin, ang, xquat[b]], axis=-1)                      # (12, 13)
    joint = jnp.stack([q, v], axis=-1).reshape(12, 2, 2)                         # (12, slot, [qpos, qvel])
    out = tab.static_feat                                  # float32: also where the physics runs in float64
    out = out.at[:, :13].set(dyn.astype(out.dtype))
    out = out.at[:, 30:32].set(joint[:, 0].astype(out.dtype))
    out = out.at[:, 41:43].set(joint[:, 1].astype(out.dtype))
    return mask_features(out, node_mask, act_mask)


def mask_features(obs: jax.Array, node_mask: jax.Array, act_mask: jax.Array) -> jax.Array:
    """Zero padded tokens and the joint entries of missing joint slots."""
    obs = obs * node_mask[:, None]
    am = act_mask.reshape(12, 2)
    obs = obs.at[:, 30:32].multiply(am[:, 0:1]).at[:, 41:43].multiply(am[:, 1:2])
    return obs


assert OBS_DIM == 52
