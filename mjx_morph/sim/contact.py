"""Plane-capsule contact frames as MuJoCo C computes them, installed into MJX's collision table.

With pyramidal friction cones the orientation of a contact's tangent frame matters: the 4 pyramid edges lie along
its first tangent and the one after. MuJoCo C (`mjc_PlaneCapsule` + `mju_makeFrame`) takes the capsule axis
projected onto the plane as the first tangent whenever the projection is non-zero. MJX 3.17's JAX collider falls
back to a fixed world axis as soon as the projection is shorter than 0.5, i.e. for every capsule steeper than 60
degrees, which is most of a standing UNIMAL's legs; the two then apply different friction pyramids and
trajectories part by centimetres within 0.5 s (measured: 2e-3 m after 9 control steps for a train robot at
MuJoCo's default solver settings, 1e-5 m with this fix).

`install()` replaces MJX's (plane, capsule) collider by one with MuJoCo C's frame rule. It patches a private table
of the pinned mujoco-mjx (3.17.0), idempotently, and only changes the tangent frame of plane-capsule contacts; the
environment installs it when it builds its model (option `c_contact_frames`, default on). Sphere-plane contacts
already agree (MJX's `make_frame` picks (0, 1, 0) like `mju_makeFrame`). Height-field and box contacts have no
MuJoCo C counterpart of the same algorithm in MJX and are left alone.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_driver, collision_primitive
from mujoco.mjx._src.types import GeomType

_ORIGINAL = collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)]


@collision_primitive.collider(ncon=2)
def plane_capsule(plane, cap):
    """Two sphere-plane contacts at the capsule's segment ends, tangent = projected capsule axis."""
    n = plane.mat[:, 2]
    axis = cap.mat[:, 2]
    t = axis - n * jnp.dot(n, axis)
    norm = jnp.linalg.norm(t)
    t = jnp.where(norm > 1e-10, t / jnp.where(norm > 1e-10, norm, 1.0), jnp.array([1.0, 0.0, 0.0]))
    frame = jnp.stack([n, t, jnp.cross(n, t)])
    radius, half = cap.size[0], cap.size[1]
    dists, poss = [], []
    for sign in (1.0, -1.0):
        centre = cap.pos + sign * half * axis
        dist = jnp.dot(centre - plane.pos, n) - radius
        dists.append(dist)
        poss.append(centre - n * (radius + 0.5 * dist))
    return jnp.stack(dists), jnp.stack(poss), jnp.stack([frame, frame])


def install(enable: bool = True) -> None:
    """Use MuJoCo C's plane-capsule frames in MJX (enable=False restores MJX's own collider)."""
    collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)] = plane_capsule if enable else _ORIGINAL


def installed() -> bool:
    return collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)] is plane_capsule
